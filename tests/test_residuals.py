"""Residual channels: a smooth mismatch is flagged in the right channel, noise is not."""

from pathlib import Path

import numpy as np
import pytest

from torchfit.residuals import locate, noise_floor, residual_channels
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
