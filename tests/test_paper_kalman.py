"""Paper Fig. 2 experiment: batch ballistic fit vs. Kalman filter and RTS smoother."""

import json

import numpy as np
import pytest
from hydra import compose, initialize_config_module

from torchfit.paper import kalman
from torchfit.run import run


def _throws(noise: float, trials: int = 20, seed: int = 3):
    settings = kalman.ThrowSettings(noise=noise)
    return settings, kalman.simulate_throws(settings, trials, np.random.default_rng(seed))


def test_simulated_throws_are_parabolas():
    settings, throws = _throws(0.0, trials=4)
    assert throws.positions.shape == (4, settings.samples, 2) and throws.future.shape == (4, 18, 2)
    # second differences of a parabola sampled at dt are (0, -g dt^2) exactly
    dt = 1 / settings.fps
    second = throws.positions[:, 2:] - 2 * throws.positions[:, 1:-1] + throws.positions[:, :-2]
    np.testing.assert_allclose(second / dt**2, np.broadcast_to([0.0, -settings.g], second.shape), atol=1e-9)
    np.testing.assert_allclose(throws.observations, throws.positions)


@pytest.mark.parametrize("fit_g", [False, True])
def test_batch_fit_is_exact_on_noise_free_data(fit_g):
    settings, throws = _throws(0.0)
    fitted = kalman.fit_ballistic(throws.times, throws.observations, None if fit_g else settings.g)
    np.testing.assert_allclose(fitted.p0, throws.p0, atol=1e-10)
    np.testing.assert_allclose(fitted.v0, throws.v0, atol=1e-9)
    np.testing.assert_allclose(fitted.g, settings.g, atol=1e-8)
    assert np.all(fitted.sigma < 1e-9)


def test_batch_standard_errors_are_calibrated():
    settings, throws = _throws(0.01, trials=400, seed=11)
    fitted = kalman.fit_ballistic(throws.times, throws.observations, None)
    z = np.concatenate([(fitted.p0 - throws.p0) / fitted.p0_se, (fitted.v0 - throws.v0) / fitted.v0_se,
                        ((fitted.g - settings.g) / fitted.g_se)[:, None]], 1)
    assert np.all(np.abs(z.std(0) - 1) < 0.15), z.std(0)
    assert abs(np.median(fitted.sigma) / settings.noise - 1) < 0.05


def test_kalman_with_zero_process_noise_is_the_batch_fit():
    """q = 0 and a diffuse prior: the filter is recursive least squares, the smoother the batch fit."""
    settings, throws = _throws(0.01)
    fitted = kalman.fit_ballistic(throws.times, throws.observations, settings.g)
    traj, vel = kalman.ballistic(fitted.p0, fitted.v0, throws.times, settings.g)
    filtered = kalman.kalman_filter(throws.times, throws.observations, 0.0, settings.noise, g=settings.g)
    smoothed = kalman.rts_smoother(filtered)
    np.testing.assert_allclose(filtered.filtered[0, :, -1, :2], traj[:, -1], atol=1e-6)
    np.testing.assert_allclose(smoothed[0, ..., :2], traj, atol=1e-6)
    np.testing.assert_allclose(smoothed[0, ..., 2:4], vel, atol=1e-5)


@pytest.mark.parametrize("model", kalman.MODELS)
def test_kalman_converges_to_truth_on_noise_free_data(model):
    settings, throws = _throws(0.0)
    run_ = kalman.kalman_filter(throws.times, throws.observations, 1e-6, 1e-6, model=model, g=settings.g)
    final = run_.filtered[0, :, -1]
    np.testing.assert_allclose(final[:, :2], throws.positions[:, -1], atol=1e-5)
    np.testing.assert_allclose(final[:, 2:4], throws.velocities[:, -1], atol=1e-3)
    if model == "constant_acceleration":
        np.testing.assert_allclose(final[:, 4:6], np.broadcast_to([0.0, -settings.g], (20, 2)), atol=1e-2)


def test_innovation_likelihood_prefers_the_true_process_noise():
    """On data with real random acceleration the likelihood picks q near the truth, not q = 0."""
    rng = np.random.default_rng(5)
    dt, steps, q_true, noise = 1 / 60, 200, 4.0, 0.01
    velocity = np.cumsum(rng.normal(0, np.sqrt(q_true * dt), (1, steps, 2)), 1) + [3.0, 4.0]
    velocity[..., 1] -= 9.81 * dt * np.arange(steps)
    positions = np.cumsum(velocity * dt, 1)
    observations = positions + noise * rng.standard_normal(positions.shape)
    grid = np.r_[0.0, np.logspace(-2, 2, 9)]
    filtered = kalman.kalman_filter(np.arange(steps) * dt, observations, grid, noise)
    q_ml = grid[np.argmax(filtered.loglik[:, 0])]
    assert 0.4 <= q_ml <= 40.0, q_ml


def test_batch_fit_beats_the_filter_on_noisy_throws():
    settings, throws = _throws(0.01, trials=40, seed=0)
    q_grid = {"cv_gravity": np.r_[0.0, np.logspace(-4, 4, 9)], "constant_acceleration": np.r_[0.0, np.logspace(-2, 6, 9)]}
    errors = kalman.evaluate(throws, settings, q_grid, [10.0])["errors"]
    batch = errors["batch (g known)"]
    for method in ("KF CV+g (q ML)", "KF CV+g (q=10)", "KF CA (q ML)", "RTS CV+g (q=10)"):
        assert np.median(batch["trajectory_rms_m"]) < 0.8 * np.median(errors[method]["trajectory_rms_m"]), method
    # a tracking-tuned filter predicts worse past the window than the physical model
    assert np.median(batch["extrapolation_rms_m"]) < 0.5 * np.median(errors["KF CV+g (q=10)"]["extrapolation_rms_m"])
    # the best-case smoother is no better than the batch fit (it is the batch fit when q = 0)
    assert np.median(errors["RTS CV+g (q ML)"]["trajectory_rms_m"]) >= 0.999 * np.median(batch["trajectory_rms_m"])


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="observations must have shape"):
        kalman.fit_ballistic(np.arange(5.0), np.zeros((2, 4, 2)))
    with pytest.raises(ValueError, match="Invalid model"):
        kalman.kalman_filter(np.arange(5.0), np.zeros((1, 5, 2)), 1.0, 0.01, model="singer")
    with pytest.raises(ValueError, match="q must be >= 0"):
        kalman.kalman_filter(np.arange(5.0), np.zeros((1, 5, 2)), -1.0, 0.01)
    with pytest.raises(ValueError, match="noise must be >= 0"):
        kalman.ThrowSettings(noise=-0.1)


def test_config_runs_quick(tmp_path):
    with initialize_config_module(config_module="torchfit.configs", version_base="1.3"):
        cfg = compose(config_name="config", overrides=["experiment=paper_kalman", "params.quick=true", "quiet=true"])
    summary = run(cfg, tmp_path)
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    assert summary["settings"]["trials"] == 10
    for name in summary["figures"].values():
        assert (tmp_path / name).stat().st_size > 10_000
    methods = summary["methods"]
    assert methods["batch (g known)"]["trajectory_rms_m"]["median"] < methods["KF CV+g (q ML)"]["trajectory_rms_m"]["median"]
