"""Residual channels: a smooth mismatch is flagged in the right channel, noise is not."""

from pathlib import Path

import numpy as np
import pytest
import torch

from torchfit.residuals import (
    CHANNELS,
    channel_values,
    huber_root,
    locate,
    locate_prediction,
    noise_floor,
    polynomial_trend,
    residual_channels,
)
from torchfit.video import load_observation

DATA = Path(__file__).resolve().parents[1] / "torchfit" / "recordings"


def discs(centres, radii, size=(96, 128)):
    """(T, H, W) bool discs; centres (T, 2) (x, y) pixels, radii (T,) pixels."""
    v, u = np.mgrid[: size[0], : size[1]]
    return np.stack([(u - cx) ** 2 + (v - cy) ** 2 <= r**2 for (cx, cy), r in zip(centres, radii)])


def test_quadratic_downward_drift_is_located():
    rng = np.random.default_rng(0)
    T = 40
    times = np.arange(T) / 60
    centres = np.stack([30 + 60 * times * 1.2, 40 + 0 * times], 1)
    jitter = rng.normal(0, 0.3, (T, 2))
    drift = np.zeros((T, 2))
    drift[:, 1] = 12 * times**2  # grows like t^2, 5 px at the end
    observed = discs(centres + jitter + drift, np.full(T, 12.0))
    fitted = discs(centres, np.full(T, 12.0))
    found = locate(residual_channels(observed, fitted, times))
    assert found["flagged"] == ["centroid_y"]
    assert found["channels"]["centroid_y"]["growth"] == "growing like t^2"
    assert "down" in found["summary"]


def test_scale_mismatch_is_located_and_pure_noise_is_not():
    rng = np.random.default_rng(1)
    T = 40
    times = np.arange(T) / 60
    centres = np.stack([40 + 30 * times, 50 + 0 * times], 1)
    radii = np.full(T, 14.0)
    fitted = discs(centres, radii)
    noisy = discs(centres + rng.normal(0, 0.3, (T, 2)), radii + rng.normal(0, 0.3, T))
    assert locate(residual_channels(noisy, fitted, times))["flagged"] == []
    shrinking = discs(centres + rng.normal(0, 0.3, (T, 2)), radii * (1 - 0.15 * times / times[-1]))
    assert locate(residual_channels(shrinking, fitted, times))["flagged"] == ["scale"]


@pytest.mark.parametrize("backward", [False, True])
def test_a_predictions_miss_is_located_growing_away_from_the_fitted_frames(backward):
    """A prediction that drifts left like t^2 away from the frames it was fitted on (3.4 px at the
    far end; forward into the last 12 frames, or backward into the first 12) is flagged in
    centroid_x alone, in words; noise alone is not, and the frames outside the part do not count."""
    rng = np.random.default_rng(2)
    T, n = 48, 12
    times = np.arange(T) / 60
    noise = {name: 0.1 for name in CHANNELS}
    values = {name: rng.normal(0, 0.1, T) for name in CHANNELS}
    held = np.zeros(T, bool)
    held[slice(T - n, T) if not backward else slice(0, n)] = True
    away = np.abs(times - (times[T - n] if not backward else times[n - 1]))  # 0 at the part's fitted side
    values["centroid_x"] = values["centroid_x"] - np.where(held, 100 * away**2, 0.0)
    values["scale"][~held] = 50.0  # outside the part: never read
    found = locate_prediction(values, held, times, noise, backward=backward)
    assert found["flagged"] == ["centroid_x"] and found["frames"] == ([T - n, T - 1] if not backward else [0, n - 1])
    x = found["channels"]["centroid_x"]
    assert x["growth"] == "growing like t^2" and x["largest"] > 2.0
    assert found["summary"].startswith("centroid_x observed left of the prediction, growing like t^2 away from the "
                                       "fitted frames, up to 3.")
    assert "at noise level: centroid_y, scale, shape, orientation" in found["summary"]
    quiet = locate_prediction({name: rng.normal(0, 0.1, T) for name in CHANNELS}, held, times, noise, backward)
    assert quiet["flagged"] == [] and quiet["summary"].startswith("at noise level")
    # the same drift within what the prediction's own spread allows there (one error of its
    # parameters, shared by every frame it predicts) is not a miss
    spread = np.where(held, 2 * (0.1 + 100 * away**2), 0.0)
    covariance = {name: np.outer(spread, spread) for name in CHANNELS}
    allowed = locate_prediction(values, held, times, noise, backward=backward, covariance=covariance)
    assert allowed["flagged"] == [] and allowed["channels"]["centroid_x"]["spread_largest"] > 6.0
    # a miss of another shape than the spread's stands out of it: a drift that turns back
    bent = dict(values, centroid_x=values["centroid_x"] + np.where(held, 4 * np.sin(away * 60 * np.pi / n), 0.0))
    assert locate_prediction(bent, held, times, noise, backward=backward, covariance=covariance)["flagged"] == \
        ["centroid_x"]


def test_a_trend_under_a_covariance_is_the_trend_of_the_whitened_values():
    """``polynomial_trend`` with a covariance is generalised least squares: the same degree,
    coefficients and significance as ordinary least squares on the values and the polynomial's
    columns whitened by hand; with ``sigma**2`` times the identity it is ``np.polyfit``'s fit."""
    rng = np.random.default_rng(5)
    n = 14
    t = np.arange(n) / 60
    values = 0.3 + 40 * t**2 + rng.normal(0, 0.1, n)
    plain = polynomial_trend(t, values, 0.1)
    same = polynomial_trend(t, values, 0.1, 0.01 * np.eye(n))
    assert same["degree"] == plain["degree"] == 2
    assert np.allclose(same["coefficients"], np.polyfit(t, values, 2), rtol=1e-9)
    assert np.isclose(same["significance"], plain["significance"], rtol=1e-12)
    a = 0.4 ** np.abs(np.subtract.outer(np.arange(n), np.arange(n)))  # AR(1), lag one 0.4
    covariance = 0.01 * a * np.outer(1 + t, 1 + t)
    got = polynomial_trend(t, values, 0.1, covariance)
    factor = np.linalg.cholesky(covariance)
    white, design = np.linalg.solve(factor, values), np.linalg.solve(factor, np.vander(t, got["degree"] + 1))
    coeffs = np.linalg.lstsq(design, white, rcond=None)[0]
    assert np.allclose(got["coefficients"], coeffs, rtol=1e-9)
    drop = np.sum(white**2) - np.sum((white - design @ coeffs) ** 2)
    assert np.isclose(got["significance"], np.sqrt(drop), rtol=1e-9)


def test_frame_correlated_noise_judged_as_independent_makes_trends_and_under_its_covariance_does_not():
    """AR(1) noise (lag one 0.4) on 12 frames, 4000 draws: judged as independent noise of its own
    standard deviation, a trend stands past 3 of its z-scores in many more draws than the
    chi-squared law allows; judged under its covariance, in about as many (chi-squared with the
    chosen degree's freedoms: 0.3-3 % for one to three)."""
    rng = np.random.default_rng(6)
    n, draws, rho = 12, 4000, 0.4
    t = np.arange(n) / 60
    covariance = rho ** np.abs(np.subtract.outer(np.arange(n), np.arange(n)))
    noise = rng.normal(size=(draws, n)) @ np.linalg.cholesky(covariance).T
    independent = np.mean([polynomial_trend(t, x, 1.0)["significance"] > 3 for x in noise])
    correlated = np.mean([polynomial_trend(t, x, 1.0, covariance)["significance"] > 3 for x in noise])
    assert correlated < 0.04 and independent > 3 * correlated, (independent, correlated)


@pytest.mark.parametrize("name", ["tshape", "box_fast"])
def test_segmentation_against_true_masks_is_at_noise_level(name):
    """A control from the independent engine: the true silhouettes miss no physics."""
    obs = load_observation(DATA / name / "video.mp4", camera=DATA / name / "camera.json")
    with np.load(DATA / name / "masks.npz") as data:
        truth = data[data.files[0]]
    found = locate(residual_channels(obs.masks, truth, np.arange(len(truth)) / obs.fps, obs.used))
    assert found["flagged"] == [], found["summary"]


def test_shape_mismatch_raises_for_bad_input():
    with pytest.raises(ValueError, match="must both be"):
        residual_channels(np.zeros((3, 4, 4)), np.zeros((2, 4, 4)), np.arange(3))


def test_noise_floor_of_frame_correlated_noise():
    # AR(1) noise of unit variance, lag-one correlation 0.4: the independent-noise estimate reads
    # it about 28 % low, the correlated one about right
    rng = np.random.default_rng(3)
    rho, n = 0.4, 20000
    x = np.empty(n)
    x[0] = rng.normal()
    for k in range(1, n):
        x[k] = rho * x[k - 1] + np.sqrt(1 - rho**2) * rng.normal()
    assert abs(noise_floor(x, rho) - 1.0) < 0.03
    assert abs(noise_floor(x) - np.sqrt((6 - 8 * rho + 2 * rho**2) / 6)) < 0.03


def test_huber_root_squares_sum_to_hubers_loss_and_pass_small_residuals():
    """Squares of huber_root are Huber's loss (r^2 within k, 2k|r| - k^2 beyond), with the sign
    kept; residuals within k pass unchanged and NaN stays NaN."""
    k = 2.0
    r = torch.tensor([0.0, 0.5, -1.9, 2.0, -2.5, 10.0, -40.0, float("nan")], dtype=torch.float64)
    out = huber_root(r, k)
    size = r.abs()
    loss = torch.where(size <= k, r * r, 2 * k * size - k * k)
    assert torch.allclose(out[:-1].square(), loss[:-1])
    assert torch.equal(torch.sign(out[:-1]), torch.sign(r[:-1]))
    assert torch.equal(out[:4], r[:4])
    assert float(out[5].square()) == pytest.approx(36.0)  # 10 noise units count 36, not 100
    assert torch.isnan(out[-1])


def test_huber_root_gradcheck_float64():
    """Finite differences agree with autograd on both sides of the threshold (C1 at k)."""
    r = torch.tensor([[-7.0, -2.3, -1.2, 0.3, 1.7, 2.6, 11.0]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: huber_root(x, 2.0), (r,))
    # the slope is continuous at k: 1 just inside, k / sqrt(2k|r| - k^2) -> 1 just outside
    edge = torch.tensor([2.0 - 1e-7, 2.0 + 1e-7], dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(huber_root(edge, 2.0).sum(), edge)
    assert torch.allclose(grad, torch.ones(2, dtype=torch.float64), atol=1e-6)


def _moments(area, centre, cov):
    return (torch.tensor(area, dtype=torch.float64), torch.tensor(centre, dtype=torch.float64),
            torch.tensor(cov, dtype=torch.float64))


def test_channel_values_gradcheck_float64_with_a_given_axis():
    """With the axes given, all five channels are smooth in both outlines' moments (finite
    differences agree with autograd on a round and an elongated pair), and with the observed
    outline's own long axis given they are those measured along it."""
    observed = _moments([900.0, 1200.0], [[40.2, 31.0], [70.5, 44.1]],
                        [[[72.0, 0.4], [0.4, 71.3]], [[160.0, 35.0], [35.0, 60.0]]])
    fitted = _moments([905.0, 1180.0], [[40.0, 31.3], [70.9, 44.0]],
                      [[[71.5, -0.3], [-0.3, 72.1]], [[150.0, 40.0], [40.0, 66.0]]])
    axis = torch.tensor([[0.6, 0.8], [0.96, 0.28]], dtype=torch.float64)

    def flat(area_o, centre_o, cov_o, area_f, centre_f, cov_f):
        cov_o, cov_f = 0.5 * (cov_o + cov_o.mT), 0.5 * (cov_f + cov_f.mT)
        return torch.stack(list(channel_values((area_o, centre_o, cov_o), (area_f, centre_f, cov_f), axis).values()))

    inputs = tuple(x.clone().requires_grad_() for x in observed + fitted)
    assert torch.autograd.gradcheck(flat, inputs)
    own = torch.linalg.eigh(observed[2] / observed[0][:, None, None])[1][..., :, -1]
    for name, value in channel_values(observed, fitted).items():
        torch.testing.assert_close(value, channel_values(observed, fitted, own)[name], rtol=0, atol=1e-12)


def test_channel_values_with_a_fixed_axis_do_not_jump_on_a_round_outline():
    """A round observed outline's long axis turns a quarter turn under a change of 1e-9 px^2 in
    its moments, and the shape channel measured along it jumps with it; along a fixed axis the
    channels move by about the change."""
    fitted = _moments([900.0], [[40.0, 31.0]], [[[72.0, 0.0], [0.0, 70.0]]])
    axis = torch.tensor([[1.0, 0.0]], dtype=torch.float64)

    def shape(delta, given):
        observed = _moments([900.0], [[40.0, 31.0]], [[[71.0 + delta, 0.0], [0.0, 71.0 - delta]]])
        return float(channel_values(observed, fitted, given)["shape"][0])

    assert abs(shape(1e-9, None) - shape(-1e-9, None)) > 0.01  # the observed axis: x, then y
    assert abs(shape(1e-9, axis) - shape(-1e-9, axis)) < 1e-10
