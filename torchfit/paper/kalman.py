"""Paper Fig. 2: a batch fit of the ballistic model vs. a Kalman filter on noisy 2D throws.

A point mass flies in a vertical plane (x right, y up, metres); a camera-like sensor samples its
position at ``fps`` with isotropic Gaussian noise. Three estimators see the same samples:

- **batch fit** (the paper's approach): linear least squares for the initial position and velocity
  of ``p(t) = p0 + v0 t + a t^2 / 2`` with ``a = (0, -g)``, g known, or g fitted as a fifth unknown.
  Solved exactly; standard errors from ``s^2 (A^T A)^-1`` with ``s`` estimated from the residuals.
- **Kalman filter**, linear, two process models: constant velocity with gravity as a known input
  (CV+g, white-noise acceleration of spectral density q, m^2/s^3) and constant acceleration with
  gravity unknown (CA, white-noise jerk, q in m^2/s^5). The filter is given the true measurement
  noise; q is chosen per trial by maximising the innovation likelihood over a grid (which includes
  q = 0), and a few fixed "tracking" values of q are reported too.
- **RTS smoother** on the same filter: the filter's best case (it uses all samples).

Everything is float64 numpy: the problem is linear and tiny, and the exact solve is the point.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

__all__ = [
    "BatchFit",
    "FilterRun",
    "ThrowSettings",
    "Throws",
    "ballistic",
    "fit_ballistic",
    "kalman_filter",
    "main",
    "rts_smoother",
    "simulate_throws",
]

MODELS = ("cv_gravity", "constant_acceleration")


@dataclass(frozen=True)
class ThrowSettings:
    """The simulated experiment.

    Attributes:
        fps: samples per second.
        samples: observed samples per throw (the window is ``(samples - 1) / fps`` s).
        noise: measurement noise standard deviation per axis, m.
        g: gravity, m/s^2 (acting along -y).
        speed: launch speed range, m/s (uniform).
        angle_deg: launch elevation range, degrees (uniform).
        horizon: how far past the last sample to predict, s.
    """

    fps: float = 60.0
    samples: int = 45
    noise: float = 0.01
    g: float = 9.81
    speed: tuple[float, float] = (3.0, 6.0)
    angle_deg: tuple[float, float] = (30.0, 60.0)
    horizon: float = 0.3

    def __post_init__(self):
        if not self.fps > 0:
            raise ValueError(f"fps must be positive, got {self.fps}")
        if self.samples < 3:
            raise ValueError(f"samples must be at least 3 (5 unknowns with g fitted need 3 samples), got {self.samples}")
        if not self.noise >= 0:
            raise ValueError(f"noise must be >= 0 m, got {self.noise}")
        if not self.horizon > 0:
            raise ValueError(f"horizon must be positive seconds, got {self.horizon}")


@dataclass
class Throws:
    """Simulated throws: truth and noisy samples.

    Attributes:
        times: (T,) sample times, s (first sample at 0).
        future_times: (H,) times past the window at the same rate, up to ``horizon``.
        p0: (B, 2) initial positions, m.  v0: (B, 2) initial velocities, m/s.
        positions: (B, T, 2) true positions.  velocities: (B, T, 2) true velocities.
        observations: (B, T, 2) noisy positions.
        future: (B, H, 2) true positions past the window.
    """

    times: np.ndarray
    future_times: np.ndarray
    p0: np.ndarray
    v0: np.ndarray
    g: float
    positions: np.ndarray
    velocities: np.ndarray
    observations: np.ndarray
    future: np.ndarray


def ballistic(p0: np.ndarray, v0: np.ndarray, times: np.ndarray, g) -> tuple[np.ndarray, np.ndarray]:
    """Free flight ``p0 + v0 t - (0, g) t^2 / 2``.

    Args:
        p0: (B, 2) m.  v0: (B, 2) m/s.  times: (T,) s.  g: float or (B,) m/s^2.

    Returns:
        (B, T, 2) positions and (B, T, 2) velocities.
    """
    g = np.broadcast_to(np.asarray(g, float), (p0.shape[0],))
    t = times[None, :, None]
    acc = np.stack([np.zeros_like(g), -g], -1)[:, None, :]  # (B, 1, 2)
    return p0[:, None] + v0[:, None] * t + 0.5 * acc * t**2, v0[:, None] + acc * t


def simulate_throws(settings: ThrowSettings, trials: int, rng: np.random.Generator) -> Throws:
    """Random throws (speed and elevation uniform in the settings' ranges) and noisy samples."""
    if trials < 1:
        raise ValueError(f"trials must be >= 1, got {trials}")
    times = np.arange(settings.samples) / settings.fps
    n_future = max(1, round(settings.horizon * settings.fps))
    future_times = times[-1] + np.arange(1, n_future + 1) / settings.fps
    speed = rng.uniform(*settings.speed, trials)
    angle = np.radians(rng.uniform(*settings.angle_deg, trials))
    v0 = np.stack([speed * np.cos(angle), speed * np.sin(angle)], -1)
    p0 = rng.uniform(-0.5, 0.5, (trials, 2))
    positions, velocities = ballistic(p0, v0, times, settings.g)
    observations = positions + settings.noise * rng.standard_normal(positions.shape)
    future, _ = ballistic(p0, v0, future_times, settings.g)
    return Throws(times, future_times, p0, v0, settings.g, positions, velocities, observations, future)


@dataclass
class BatchFit:
    """Least-squares ballistic fit of every trial.

    Attributes:
        p0, v0: (B, 2) estimates.  g: (B,) (the given value when g is known).
        p0_se, v0_se: (B, 2) standard errors.  g_se: (B,) (zeros when g is known).
        sigma: (B,) noise estimated from the residuals, m.
    """

    p0: np.ndarray
    v0: np.ndarray
    g: np.ndarray
    p0_se: np.ndarray
    v0_se: np.ndarray
    g_se: np.ndarray
    sigma: np.ndarray


def fit_ballistic(times: np.ndarray, observations: np.ndarray, g: float | None = None) -> BatchFit:
    """Batch least squares of the ballistic model to all samples at once (exact linear solve).

    Unknowns ``(x0, vx, y0, vy[, g])``; residuals are stacked ``[x_1..x_T, y_1..y_T]``.

    Args:
        times: (T,) s.  observations: (B, T, 2) m.
        g: known gravity, m/s^2, or ``None`` to fit it.

    Returns:
        :class:`BatchFit`; covariance ``s^2 (A^T A)^-1`` with ``s^2 = RSS / (2T - p)``.
    """
    observations = np.asarray(observations, float)
    if observations.ndim != 3 or observations.shape[1:] != (len(times), 2):
        raise ValueError(f"observations must have shape (B, {len(times)}, 2), got {observations.shape}")
    n = len(times)
    zero, one = np.zeros(n), np.ones(n)
    columns = [np.r_[one, zero], np.r_[times, zero], np.r_[zero, one], np.r_[zero, times]]
    if g is None:
        columns.append(np.r_[zero, -0.5 * times**2])
    design = np.stack(columns, 1)  # (2T, p)
    target = np.concatenate([observations[..., 0], observations[..., 1]], 1).T  # (2T, B)
    if g is not None:
        target = target + np.r_[zero, 0.5 * g * times**2][:, None]
    dof = 2 * n - design.shape[1]
    if dof < 1:
        raise ValueError(f"{n} samples cannot give a noise estimate for {design.shape[1]} unknowns")
    theta, *_ = np.linalg.lstsq(design, target, rcond=None)  # (p, B)
    residual = target - design @ theta
    sigma = np.sqrt((residual**2).sum(0) / dof)
    se = sigma[None] * np.sqrt(np.diag(np.linalg.inv(design.T @ design)))[:, None]  # (p, B)
    b = observations.shape[0]
    g_hat = theta[4] if g is None else np.full(b, float(g))
    g_se = se[4] if g is None else np.zeros(b)
    return BatchFit(theta[[0, 2]].T, theta[[1, 3]].T, g_hat, se[[0, 2]].T, se[[1, 3]].T, g_se, sigma)


def _process_model(model: str, dt: float, g: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Transition F, unit process noise Q (per unit q), input u, measurement H; state axes interleaved.

    CV+g state (x, y, vx, vy); CA state (x, y, vx, vy, ax, ay). Q is the exact discretisation of
    continuous white noise on acceleration (CV) or jerk (CA).
    """
    if model == "cv_gravity":
        f1 = np.array([[1.0, dt], [0.0, 1.0]])
        q1 = np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        control = np.array([0.0, -0.5 * g * dt**2, 0.0, -g * dt])
    elif model == "constant_acceleration":
        f1 = np.array([[1.0, dt, dt**2 / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
        q1 = np.array([[dt**5 / 20, dt**4 / 8, dt**3 / 6], [dt**4 / 8, dt**3 / 3, dt**2 / 2],
                       [dt**3 / 6, dt**2 / 2, dt]])
        control = np.zeros(6)
    else:
        raise ValueError(f'Invalid model "{model}". Must be one of {MODELS}')
    eye2 = np.eye(2)
    measure = np.kron(np.eye(1, len(f1)), eye2)  # (2, n)
    return np.kron(f1, eye2), np.kron(q1, eye2), control, measure


@dataclass
class FilterRun:
    """A Kalman filter over all trials for every q.

    Attributes:
        q: (Q,) process noise spectral densities.
        filtered: (Q, B, T, n) filtered means.  filtered_cov: (Q, B, T, n, n).
        predicted: (Q, B, T, n) one-step predictions (``predicted[:, :, 0]`` is the prior).
        predicted_cov: (Q, B, T, n, n).
        loglik: (Q, B) innovation log-likelihood, leaving out the first n/2 samples (the diffuse start).
        transition: (n, n) F.  control: (n,) u.
    """

    model: str
    q: np.ndarray
    filtered: np.ndarray
    filtered_cov: np.ndarray
    predicted: np.ndarray
    predicted_cov: np.ndarray
    loglik: np.ndarray
    transition: np.ndarray
    control: np.ndarray


def kalman_filter(times: np.ndarray, observations: np.ndarray, q, noise: float, *, model: str = "cv_gravity",
                  g: float = 9.81, prior_std: float = 100.0) -> FilterRun:
    """Linear Kalman filter (Joseph-form update) from a diffuse zero-mean prior.

    Args:
        times: (T,) uniformly spaced, s.  observations: (B, T, 2) m.
        q: scalar or (Q,) process noise spectral densities (m^2/s^3 for CV+g, m^2/s^5 for CA).
        noise: measurement noise standard deviation given to the filter, m.
        model: ``cv_gravity`` (gravity a known input) or ``constant_acceleration``.
        prior_std: prior standard deviation of every state component at the first sample.
    """
    observations = np.asarray(observations, float)
    if observations.ndim != 3 or observations.shape[1:] != (len(times), 2):
        raise ValueError(f"observations must have shape (B, {len(times)}, 2), got {observations.shape}")
    if not noise > 0:
        raise ValueError(f"the filter's noise must be positive, got {noise}")
    q = np.atleast_1d(np.asarray(q, float))
    if np.any(q < 0):
        raise ValueError(f"q must be >= 0, got {q}")
    steps = np.diff(times)
    if len(times) > 1 and not np.allclose(steps, steps[0]):
        raise ValueError("times must be uniformly spaced")
    dt = float(steps[0]) if len(times) > 1 else 1.0
    transition, unit_noise, control, measure = _process_model(model, dt, g)
    n = len(transition)
    n_q, (b, t_len, _) = len(q), observations.shape
    process = q[:, None, None, None] * unit_noise  # (Q, 1, n, n)
    meas_cov = noise**2 * np.eye(2)
    mean = np.zeros((n_q, b, n))
    cov = np.broadcast_to(prior_std**2 * np.eye(n), (n_q, b, n, n)).copy()
    filtered = np.empty((n_q, b, t_len, n))
    filtered_cov = np.empty((n_q, b, t_len, n, n))
    predicted = np.empty_like(filtered)
    predicted_cov = np.empty_like(filtered_cov)
    loglik = np.zeros((n_q, b))
    eye = np.eye(n)
    for k in range(t_len):
        if k > 0:
            mean = mean @ transition.T + control
            cov = transition @ cov @ transition.T + process
        predicted[:, :, k], predicted_cov[:, :, k] = mean, cov
        innovation = observations[None, :, k] - mean @ measure.T  # (Q, B, 2)
        s = measure @ cov @ measure.T + meas_cov  # (Q, B, 2, 2)
        gain = cov @ measure.T @ np.linalg.inv(s)  # (Q, B, n, 2)
        mean = mean + (gain @ innovation[..., None])[..., 0]
        joseph = eye - gain @ measure
        cov = joseph @ cov @ np.swapaxes(joseph, -1, -2) + gain @ meas_cov @ np.swapaxes(gain, -1, -2)
        filtered[:, :, k], filtered_cov[:, :, k] = mean, cov
        if k >= n // 2:
            solved = np.linalg.solve(s, innovation[..., None])[..., 0]
            loglik -= 0.5 * (np.linalg.slogdet(s)[1] + (innovation * solved).sum(-1) + 2 * math.log(2 * math.pi))
    return FilterRun(model, q, filtered, filtered_cov, predicted, predicted_cov, loglik, transition, control)


def rts_smoother(run: FilterRun) -> np.ndarray:
    """Rauch-Tung-Striebel smoothed means, (Q, B, T, n): every estimate uses all samples."""
    smoothed = run.filtered.copy()
    for k in range(run.filtered.shape[2] - 2, -1, -1):
        # C = P_k F^T P_{k+1|k}^-1, via a solve with the symmetric predicted covariance
        cross = run.filtered_cov[:, :, k] @ run.transition.T
        gain = np.swapaxes(np.linalg.solve(run.predicted_cov[:, :, k + 1], np.swapaxes(cross, -1, -2)), -1, -2)
        correction = smoothed[:, :, k + 1] - run.predicted[:, :, k + 1]
        smoothed[:, :, k] = run.filtered[:, :, k] + (gain @ correction[..., None])[..., 0]
    return smoothed


def _extrapolate(state: np.ndarray, tau: np.ndarray, model: str, g: float) -> np.ndarray:
    """The process model's noise-free prediction from a state (B, n) over delays tau (H,): (B, H, 2)."""
    acc = state[:, None, 4:6] if model == "constant_acceleration" else np.array([0.0, -g])
    t = tau[None, :, None]
    return state[:, None, 0:2] + state[:, None, 2:4] * t + 0.5 * acc * t**2


def _rms(err: np.ndarray) -> np.ndarray:
    """(B, T, 2) errors -> (B,) RMS of the Euclidean error over T."""
    return np.sqrt((err**2).sum(-1).mean(-1))


def _stats(values: np.ndarray) -> dict:
    values = np.asarray(values, float)
    return {"median": float(np.median(values)), "mean": float(values.mean()),
            "p90": float(np.percentile(values, 90)), "max": float(values.max())}


def _pick(values: np.ndarray, index: np.ndarray) -> np.ndarray:
    """values (Q, B, ...) -> (B, ...) at q index[b] per trial."""
    return values[index, np.arange(values.shape[1])]


def _method_errors(throws: Throws, traj: np.ndarray, vel: np.ndarray, future: np.ndarray,
                   p0=None, v0=None, g=None) -> dict:
    """Per-trial errors of one method (arrays (B,))."""
    # velocity from sample 2 on: before that a forward filter's velocity is still its prior
    errors = {"trajectory_rms_m": _rms(traj - throws.positions),
              "velocity_rms_ms": _rms(vel[:, 2:] - throws.velocities[:, 2:]),
              "extrapolation_rms_m": _rms(future - throws.future),
              "extrapolation_end_m": np.linalg.norm(future[:, -1] - throws.future[:, -1], axis=-1)}
    if p0 is not None:
        errors["p0_error_m"] = np.linalg.norm(p0 - throws.p0, axis=-1)
        errors["v0_error_ms"] = np.linalg.norm(v0 - throws.v0, axis=-1)
    if g is not None:
        errors["g_error_ms2"] = np.abs(g - throws.g)
    return errors


def evaluate(throws: Throws, settings: ThrowSettings, q_grid: dict, q_fixed: list[float]) -> dict:
    """Every method on every trial: per-trial error arrays, keyed by method, plus the estimates.

    Returns:
        ``{"errors": {method: {metric: (B,)}}, "q_ml": {model: (B,)}, "sweep": {...},
        "estimates": {method: (B, T, 2) trajectory}, "futures": {method: (B, H, 2) prediction
        past the window}, "calibration": {...}}``.
    """
    times, obs, g = throws.times, throws.observations, settings.g
    tau = throws.future_times - times[-1]
    errors, estimates, futures, q_ml, sweep = {}, {}, {}, {}, {}

    for label, g_known in (("batch (g known)", g), ("batch (g fitted)", None)):
        fitted = fit_ballistic(times, obs, g_known)
        traj, vel = ballistic(fitted.p0, fitted.v0, times, fitted.g)
        future, _ = ballistic(fitted.p0, fitted.v0, throws.future_times, fitted.g)
        errors[label] = _method_errors(throws, traj, vel, future, fitted.p0, fitted.v0,
                                       fitted.g if g_known is None else None)
        estimates[label], futures[label] = traj, future
        if g_known is None:
            batch_g_fitted = fitted
        else:
            batch_g_known = fitted

    for model, short in (("cv_gravity", "CV+g"), ("constant_acceleration", "CA")):
        grid = np.asarray(q_grid[model], float)
        fixed = np.asarray(q_fixed if model == "cv_gravity" else [], float)
        run = kalman_filter(times, obs, np.r_[grid, fixed], settings.noise, model=model, g=g)
        smoothed = rts_smoother(run)
        best = np.argmax(run.loglik[: len(grid)], 0)  # (B,)
        q_ml[model] = grid[best]
        # the filter's final state equals the smoother's, so both extrapolate the same way
        future_all = np.stack([_extrapolate(run.filtered[i, :, -1], tau, model, g) for i in range(len(run.q))])
        traj_f, traj_s = run.filtered[..., 0:2], smoothed[..., 0:2]
        vel_f, vel_s = run.filtered[..., 2:4], smoothed[..., 2:4]
        sweep[model] = {
            "q": grid.tolist(),
            "kf_trajectory_rms_median": np.median(_rms(traj_f[: len(grid)] - throws.positions), -1).tolist(),
            "rts_trajectory_rms_median": np.median(_rms(traj_s[: len(grid)] - throws.positions), -1).tolist(),
            "extrapolation_rms_median": np.median(_rms(future_all[: len(grid)] - throws.future), -1).tolist(),
            "mean_loglik": run.loglik[: len(grid)].mean(-1).tolist(),
        }
        g_rts = g_kf = None
        if model == "constant_acceleration":
            g_kf = -_pick(run.filtered[..., -1, 5], best)
            g_rts = -_pick(smoothed[..., 5], best).mean(-1)
        errors[f"KF {short} (q ML)"] = _method_errors(throws, _pick(traj_f, best), _pick(vel_f, best),
                                                       _pick(future_all, best), g=g_kf)
        errors[f"RTS {short} (q ML)"] = _method_errors(
            throws, _pick(traj_s, best), _pick(vel_s, best), _pick(future_all, best),
            _pick(smoothed[..., 0, 0:2], best), _pick(smoothed[..., 0, 2:4], best), g_rts)
        estimates[f"KF {short} (q ML)"] = _pick(traj_f, best)
        estimates[f"RTS {short} (q ML)"] = _pick(traj_s, best)
        futures[f"KF {short} (q ML)"] = _pick(future_all, best)
        for j, q in enumerate(fixed):
            i = len(grid) + j
            errors[f"KF {short} (q={q:g})"] = _method_errors(throws, traj_f[i], vel_f[i], future_all[i])
            errors[f"RTS {short} (q={q:g})"] = _method_errors(throws, traj_s[i], vel_s[i], future_all[i],
                                                              smoothed[i, :, 0, 0:2], smoothed[i, :, 0, 2:4])
            estimates[f"KF {short} (q={q:g})"] = traj_f[i]
            estimates[f"RTS {short} (q={q:g})"] = traj_s[i]
            futures[f"KF {short} (q={q:g})"] = future_all[i]

    calibration = {}
    for label, fitted in (("batch (g known)", batch_g_known), ("batch (g fitted)", batch_g_fitted)):
        z = np.concatenate([((fitted.p0 - throws.p0) / fitted.p0_se), ((fitted.v0 - throws.v0) / fitted.v0_se)], 1)
        names = ["x0", "y0", "vx0", "vy0"]
        se = [fitted.p0_se[:, 0], fitted.p0_se[:, 1], fitted.v0_se[:, 0], fitted.v0_se[:, 1]]
        err = [fitted.p0[:, 0] - throws.p0[:, 0], fitted.p0[:, 1] - throws.p0[:, 1],
               fitted.v0[:, 0] - throws.v0[:, 0], fitted.v0[:, 1] - throws.v0[:, 1]]
        if fitted is batch_g_fitted:
            z = np.concatenate([z, ((fitted.g - throws.g) / fitted.g_se)[:, None]], 1)
            names.append("g")
            se.append(fitted.g_se)
            err.append(fitted.g - throws.g)
        calibration[label] = {
            name: {"mean_se": float(np.mean(s)), "rms_error": float(np.sqrt(np.mean(e**2))),
                   "z_std": float(np.std(z[:, i])), "coverage_95": float(np.mean(np.abs(z[:, i]) < 1.96))}
            for i, (name, s, e) in enumerate(zip(names, se, err))}
        calibration[label]["sigma_estimate_median_m"] = float(np.median(fitted.sigma))
    return {"errors": errors, "q_ml": q_ml, "sweep": sweep, "estimates": estimates, "futures": futures,
            "calibration": calibration}


def _figure_trial(throws: Throws, evaluation: dict, settings: ThrowSettings, trial: int, q_show: float,
                  path: Path) -> None:
    """Fig. 2 of the paper: one throw, batch fit (left) and Kalman filter (right); errors vs time below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    est, fut, errs = evaluation["estimates"], evaluation["futures"], evaluation["errors"]
    obs = throws.observations[trial]
    dense = np.linspace(0.0, throws.future_times[-1], 200)
    truth_dense, _ = ballistic(throws.p0[trial:trial + 1], throws.v0[trial:trial + 1], dense, settings.g)
    fit = fit_ballistic(throws.times, throws.observations[trial:trial + 1], settings.g)
    fit_dense, _ = ballistic(fit.p0, fit.v0, dense, settings.g)
    window = dense <= throws.times[-1] + 1e-12
    fig, axes = plt.subplots(2, 2, figsize=(12, 8.4), sharex="row", sharey="row",
                             gridspec_kw={"height_ratios": [1.25, 1]})
    top, bottom = axes
    for ax in top:
        ax.plot(truth_dense[0, :, 0], truth_dense[0, :, 1], color="0.6", lw=4, alpha=0.5, label="truth")
        ax.plot(obs[:, 0], obs[:, 1], "k.", ms=4, label=f"observations (σ = {settings.noise * 1000:g} mm)")
        ax.plot(throws.future[trial, :, 0], throws.future[trial, :, 1], "o", mfc="none", mec="0.6", ms=4,
                label=f"truth, next {settings.horizon:g} s (not observed)")
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
    top[0].set_ylabel("y (m)")
    top[0].plot(fit_dense[0, window, 0], fit_dense[0, window, 1], "C0", lw=1.5, label="batch fit (g known)")
    top[0].plot(fit_dense[0, ~window, 0], fit_dense[0, ~window, 1], "C0--", lw=1.5, label="batch fit, extrapolated")
    top[0].set_title("Batch least squares of the ballistic model")
    q_ml = evaluation["q_ml"]["cv_gravity"][trial]
    curves = [(f"KF CV+g (q={q_show:g})", "C3", f"KF, q = {q_show:g} m²/s³"),
              ("KF CV+g (q ML)", "C2", f"KF, q by max. likelihood (= {q_ml:g})"),
              ("RTS CV+g (q ML)", "C1", "RTS smoother, same q")]
    for key, color, label in curves:
        top[1].plot(est[key][trial, :, 0], est[key][trial, :, 1], ".-", color=color, lw=1, ms=3, label=label)
    top[1].set_title("Kalman filter, constant velocity + gravity input")
    for ax in top:
        ax.legend(fontsize=7, loc="lower center")

    t_all = np.r_[throws.times, throws.future_times]
    truth_all = np.concatenate([throws.positions[trial], throws.future[trial]])
    noise_err = np.linalg.norm(obs - throws.positions[trial], axis=-1) * 1000
    for ax in bottom:
        ax.plot(throws.times, noise_err, "k.", ms=3, alpha=0.5, label="observation error")
        ax.axvspan(throws.times[-1], t_all[-1], color="0.92", zorder=0)
        ax.set_yscale("log")
        ax.set_xlabel("time (s); shaded: prediction past the last sample")
        ax.grid(True, which="both", alpha=0.3)
    bottom[0].set_ylabel("position error vs truth (mm)")

    def error(key: str) -> np.ndarray:
        return np.linalg.norm(np.concatenate([est[key][trial], fut[key][trial]]) - truth_all, axis=-1) * 1000

    batch = "batch (g known)"
    bottom[0].plot(t_all, error(batch), "C0", lw=1.5,
                   label=f"batch fit: RMS {errs[batch]['trajectory_rms_m'][trial] * 1000:.1f} mm in window, "
                         f"{errs[batch]['extrapolation_rms_m'][trial] * 1000:.1f} mm predicted")
    for key, color, label in curves:
        if key.startswith("RTS"):  # smoothed in the window; past it the same prediction as the filter
            series = np.r_[np.linalg.norm(est[key][trial] - throws.positions[trial], axis=-1) * 1000,
                           np.full(len(throws.future_times), np.nan)]
        else:
            series = error(key)
        bottom[1].plot(t_all, series, color=color, lw=1.2,
                       label=f"{label}: RMS {errs[key]['trajectory_rms_m'][trial] * 1000:.1f} mm in window"
                             + ("" if key.startswith("RTS") else
                                f", {errs[key]['extrapolation_rms_m'][trial] * 1000:.1f} mm predicted"))
    for ax in bottom:
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(f"Noisy 2D ballistic data, {settings.samples} samples at {settings.fps:g} Hz "
                 f"(trial {trial}, launch {np.linalg.norm(throws.v0[trial]):.1f} m/s)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _figure_errors(evaluation: dict, methods: list[str], path: Path) -> None:
    """Box plots of trajectory and extrapolation errors over trials, and the KF error vs q sweep."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    errs = evaluation["errors"]
    fig, axes = plt.subplots(1, 3, figsize=(16, 5.2))
    for ax, metric, title in ((axes[0], "trajectory_rms_m", "RMS position error over the observed window"),
                              (axes[1], "extrapolation_rms_m", "RMS position error, extrapolated window")):
        data = [errs[m][metric] * 1000 for m in methods]
        ax.boxplot(data, orientation="horizontal", whis=(5, 95), showfliers=False)
        ax.set_yticks(range(1, len(methods) + 1), methods, fontsize=8)
        ax.set_xscale("log")
        low = min(np.percentile(d, 5) for d in data) * 0.8
        high = max(np.percentile(d, 95) for d in data) * 1.25
        ax.set_xticks([t for t in (0.5, 1, 2, 5, 10, 20, 50, 100, 200, 500) if low <= t <= high])
        ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("mm (box: quartiles, whiskers: 5-95 %)")
        ax.set_title(title, fontsize=10)
        ax.invert_yaxis()
        ax.grid(True, axis="x", which="both", alpha=0.3)
    axes[1].tick_params(axis="y", labelleft=False)
    sweep = evaluation["sweep"]["cv_gravity"]
    q = np.asarray(sweep["q"])
    floor = q[q > 0].min() / 10
    qp = np.where(q > 0, q, floor)
    ax = axes[2]
    ax.plot(qp, np.asarray(sweep["kf_trajectory_rms_median"]) * 1000, "C3o-", ms=3, label="KF filtered, window")
    ax.plot(qp, np.asarray(sweep["rts_trajectory_rms_median"]) * 1000, "C1o-", ms=3, label="RTS smoothed, window")
    ax.plot(qp, np.asarray(sweep["extrapolation_rms_median"]) * 1000, "C5o-", ms=3, label="KF prediction, extrapolated")
    for metric, style, label in (("trajectory_rms_m", "C0--", "batch fit, window"),
                                 ("extrapolation_rms_m", "C0:", "batch fit, extrapolated")):
        ax.axhline(np.median(errs["batch (g known)"][metric]) * 1000, color="C0", ls=style[2:], label=label)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(f"process noise q (m²/s³); leftmost point is q = 0 (drawn at {floor:g})")
    ax.set_ylabel("median RMS position error (mm)")
    ax.set_title("CV+g Kalman filter vs its process noise q", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(out_dir: Path, *, quick: bool = False, device="cpu", dtype=torch.float32, progress=print, seed: int = 0,
         trials: int = 200, quick_trials: int = 10, noise: float = 0.01, fps: float = 60.0, samples: int = 45,
         horizon: float = 0.3, g: float = 9.81, speed: tuple = (3.0, 6.0), angle_deg: tuple = (30.0, 60.0),
         q_fixed: tuple = (1.0, 10.0), figure_trial: int = 0) -> dict:
    """Run the Fig. 2 comparison over random throws; write figures and summary.json into out_dir.

    ``device`` and ``dtype`` are accepted for the task interface and unused: the estimators are
    exact float64 numpy solves.

    Returns:
        The summary (also written as ``summary.json``).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    settings = ThrowSettings(fps=float(fps), samples=int(samples), noise=float(noise), g=float(g),
                             speed=tuple(float(v) for v in speed), angle_deg=tuple(float(v) for v in angle_deg),
                             horizon=float(horizon))
    n_trials = int(quick_trials if quick else trials)
    if not 0 <= figure_trial < n_trials:
        raise ValueError(f"figure_trial must be in [0, {n_trials}), got {figure_trial}")
    q_fixed = [float(q) for q in q_fixed]
    if any(q < 0 for q in q_fixed):
        raise ValueError(f"q_fixed must be >= 0, got {q_fixed}")
    q_grid = {"cv_gravity": np.r_[0.0, np.logspace(-4, 4, 17)],
              "constant_acceleration": np.r_[0.0, np.logspace(-2, 6, 17)]}
    rng = np.random.default_rng(seed)
    throws = simulate_throws(settings, n_trials, rng)
    progress(f"paper_kalman: {n_trials} throws, {settings.samples} samples at {settings.fps:g} Hz, "
             f"noise {settings.noise * 1000:g} mm")
    evaluation = evaluate(throws, settings, q_grid, q_fixed)
    errors = evaluation["errors"]
    methods = list(errors)
    table = {m: {metric: _stats(values) for metric, values in errors[m].items()} for m in methods}
    for m in methods:
        progress(f"  {m:24s} window {table[m]['trajectory_rms_m']['median'] * 1000:7.2f} mm, "
                 f"extrapolated {table[m]['extrapolation_rms_m']['median'] * 1000:7.2f} mm (medians)")
    batch = errors["batch (g known)"]["trajectory_rms_m"]
    # ties (an RTS smoother with q = 0 is the batch fit, to 1e-8 m) count for neither side
    head_to_head = {m: {"batch_better_by_1pct": float(np.mean(batch < 0.99 * errors[m]["trajectory_rms_m"])),
                        "batch_worse_by_1pct": float(np.mean(errors[m]["trajectory_rms_m"] < 0.99 * batch)),
                        "median_error_ratio": float(np.median(errors[m]["trajectory_rms_m"] / batch))}
                    for m in methods if m != "batch (g known)"}
    figures = {"trial": "fig2_trial.png", "errors": "errors.png"}
    q_show = max(q_fixed) if q_fixed else None
    if q_show is not None:
        _figure_trial(throws, evaluation, settings, figure_trial, q_show, out_dir / figures["trial"])
    else:
        figures.pop("trial")
    box_methods = [m for m in methods if not m.startswith("RTS") or "ML" in m]
    _figure_errors(evaluation, box_methods, out_dir / figures["errors"])
    q_ml = evaluation["q_ml"]
    summary = {
        "settings": {"trials": n_trials, "seed": int(seed), "fps": settings.fps, "samples": settings.samples,
                     "window_s": float(throws.times[-1]), "noise_m": settings.noise, "g": settings.g,
                     "speed_ms": list(settings.speed), "angle_deg": list(settings.angle_deg),
                     "horizon_s": float(throws.future_times[-1] - throws.times[-1]),
                     "horizon_samples": len(throws.future_times), "q_fixed_cv": q_fixed,
                     "q_grid": {k: v.tolist() for k, v in q_grid.items()},
                     "filter_noise": "the true measurement noise", "prior_std": 100.0},
        "methods": table,
        "vs_batch_trajectory": head_to_head,
        "q_ml": {model: {"median": float(np.median(v)), "fraction_zero": float(np.mean(v == 0)),
                         "p90": float(np.percentile(v, 90))} for model, v in q_ml.items()},
        "sweep": evaluation["sweep"],
        "calibration": evaluation["calibration"],
        "figures": figures,
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    return json.loads(json.dumps(summary))
