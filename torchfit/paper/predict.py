"""Paper Figs. 4 and 5: fit a short clip, predict the rest, and how far to trust the prediction.

A body spinning about its major axis (stable) and one spinning about its intermediate axis
(unstable: the Dzhanibekov flip) are each fitted on their first ``window`` frames and simulated
forward over the whole clip; the prediction is scored against the truth frame by frame (IoU of
the silhouettes with the true masks, rotation error modulo the shape's symmetry).

What the paper could not give is the spread. Near the optimum the loss is a sum of squared
residuals ``L(p) = |r(p)|²`` (the silhouette differences per crop pixel and the centroid offsets,
see :func:`silhouette_residuals`) over the 14 parameters ``p`` (rotation vector, centre of mass,
its velocity, angular velocity, gravity tilt and roll). Its Gauss-Newton curvature gives the
Laplace approximation of the posterior, ``Cov(p) = s² (JᵀJ)⁻¹`` with ``J = ∂r/∂p`` and the
residual variance ``s² = |r|² / (N - 14)``. ``J`` comes from autograd: each column ``J e_i`` is a
forward-mode product, obtained as the derivative of the reverse-mode product ``Jᵀ v`` with respect
to ``v`` (the "double-vjp" trick; the rasteriser's backward pass is itself differentiable).
Initial states drawn from that Gaussian are propagated over the clip, giving a band of predicted
errors. The pixel residuals are not independent (neighbouring edge pixels move together), so
``s² (JᵀJ)⁻¹`` understates the spread; by default (``covariance="frames"``) the covariance is the
cluster-robust sandwich with each frame's residuals one cluster, which allows any correlation
inside a frame (not between frames). ``noise_inflation`` scales the standard deviations.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..dynamics import integrate
from ..losses import coverage_residuals
from ..render import render_silhouettes
from ..report import score_against_truth
from ..search import Candidates, Problem, rk4_step
from ._recording import (
    as_result,
    candidate_poses,
    hard_silhouettes,
    iou,
    load_recording,
    rotation_error_deg,
    search_settings,
)

__all__ = [
    "fit_covariance",
    "laplace_samples",
    "levenberg_marquardt",
    "main",
    "perturb",
    "residual_jacobian",
    "silhouette_residuals",
    "step_size",
]

N_PARAMS = 14  # rotation vector 3, centre of mass 3, its velocity 3, angular velocity 3, tilt and roll
PROBE_SPIN = 0.05  # rad/s, the spin error whose effect past the clip is shown for reference


def step_size(problem: Problem, cands: Candidates, frames: int) -> float:
    """The search's RK4 step for these candidates (fixed here so the residuals are smooth in p)."""
    return rk4_step(problem, cands.omega, problem.times[:frames])


def silhouette_residuals(problem: Problem, cands: Candidates, *, crop: int, sigma: float,
                         step: float, centroid_weight: float = 1.0) -> Tensor:
    """Residuals whose squared sum is the search's loss (:func:`torchfit.losses.silhouette_loss`).

    Args:
        problem: the fitted frames.
        cands: B candidates.
        crop, sigma: crop size (pixels) and edge width (crop pixels) of the rendering.
        step: RK4 step, seconds.
        centroid_weight: weight of the centroid term, as in the loss.

    Returns:
        (B, N) residuals, ``N = T (crop² + 2)``: per frame the coverage differences scaled by
        ``sqrt(w_t / (crop² Σw))`` and the centroid offsets (crop units) scaled by
        ``sqrt(centroid_weight w_t / Σw)``.
    """
    frames = len(problem.times)
    traj = integrate(cands.state(problem.body), problem.times, problem.body, cands.gravity(problem.g),
                     step_size=step)
    windows = problem.windows(crop).expand(len(cands), frames, 3)
    cover = render_silhouettes(problem.mesh, problem.camera, traj.rot, traj.position, windows,
                               size=(crop, crop), sigma=sigma)  # (B, T, h, w)
    return coverage_residuals(cover, problem.targets(crop), problem.used.to(cover.dtype), centroid_weight).flatten(1)


def perturb(cands: Candidates, offsets: Tensor) -> Candidates:
    """M candidates ``offsets`` (M, 14) away from one candidate, in the search's parameters
    (rotation vector about its orientation, centre of mass, its velocity, spin, tilt and roll)."""
    if offsets.dim() != 2 or offsets.shape[1] != N_PARAMS:
        raise ValueError(f"offsets must have shape (M, {N_PARAMS}), got {tuple(offsets.shape)}")
    count = len(offsets)
    base = cands.select(torch.tensor([0])).rebase()
    parts = offsets.split([3, 3, 3, 3, 2], dim=1)
    return Candidates(base.base.expand(count, 4), parts[0], base.com + parts[1], base.com_velocity + parts[2],
                      base.omega + parts[3], base.gravity_angles + parts[4])


def residual_jacobian(residuals: Callable[[Tensor], Tensor], params: Tensor) -> tuple[Tensor, Tensor]:
    """Residuals and their Jacobian by autograd.

    Each column ``J e_i`` is the derivative of ``Jᵀ v`` (one reverse pass, graph kept) with
    respect to ``v``: P extra backward passes instead of one per residual.

    Args:
        residuals: ``(P,) -> (N,)``, differentiable twice in reverse mode.
        params: (P,) the point.

    Returns:
        (N,) residuals and (N, P) Jacobian.
    """
    params = params.detach().clone().requires_grad_()
    res = residuals(params)
    probe = torch.zeros_like(res, requires_grad=True)
    (transposed,) = torch.autograd.grad(res, params, probe, create_graph=True)  # (P,) = Jᵀ v
    eye = torch.eye(len(params), dtype=params.dtype, device=params.device)
    columns = [torch.autograd.grad(transposed, probe, eye[i], retain_graph=i < len(params) - 1)[0]
               for i in range(len(params))]
    return res.detach(), torch.stack(columns, -1)


def levenberg_marquardt(residuals: Callable[[Tensor], Tensor], params: Tensor, steps: int,
                        damping: float = 1e-3) -> tuple[Tensor, list[float]]:
    """Damped Gauss-Newton (Marquardt's scaling) on ``|r(p)|²`` from ``params``.

    Returns:
        (P,) the point reached and the loss before each step and at the end.
    """
    params = params.detach().clone()
    res, jac = residual_jacobian(residuals, params)
    losses = [float(res.square().sum())]
    for _ in range(steps):
        normal = jac.T @ jac
        gradient = jac.T @ res
        for _ in range(8):  # raise the damping until a step lowers the loss
            step = -torch.linalg.solve(normal + damping * torch.diag(normal.diagonal()), gradient)
            with torch.no_grad():
                trial = float(residuals(params + step).square().sum())
            if trial < losses[-1]:
                damping = max(damping / 3, 1e-9)
                break
            damping *= 4
        else:
            break
        params = params + step
        res, jac = residual_jacobian(residuals, params)
        losses.append(float(res.square().sum()))
    return params, losses


def fit_covariance(jacobian: Tensor, residuals: Tensor, *, clusters: int | None = None) -> Tensor:
    """The fit's (P, P) parameter covariance at a least-squares optimum.

    ``clusters=None``: the Laplace (Gauss-Newton) covariance ``s² (JᵀJ)⁻¹``, ``s² = |r|² / (N - P)``,
    which takes the N residuals as independent. ``clusters=C``: the residuals are C equal,
    consecutive blocks (frames) that may be correlated inside but not with each other, and the
    covariance is the cluster-robust sandwich ``(JᵀJ)⁻¹ (Σ_c g_c g_cᵀ) (JᵀJ)⁻¹ · C'/(C' - 1)`` with
    ``g_c = J_cᵀ r_c`` a block's gradient and C' the blocks with any residual (frames left out
    have none). Neighbouring edge pixels of a silhouette move together, so the per-frame sandwich
    is the honest one for pixel residuals.

    Directions the silhouettes do not constrain (eigenvalues of JᵀJ below 1e-12 of the largest)
    get zero variance rather than an infinite one.

    Args:
        jacobian: (N, P); residuals: (N,).
    """
    n_res, n_par = jacobian.shape
    values, vectors = torch.linalg.eigh(jacobian.T @ jacobian)
    keep = values > 1e-12 * values.max()
    inv = torch.where(keep, 1.0 / values.clamp(min=1e-300), torch.zeros_like(values))
    bread = (vectors * inv) @ vectors.T
    if clusters is None:
        return float(residuals.square().sum()) / max(n_res - n_par, 1) * bread
    if clusters < 2 or n_res % clusters:
        raise ValueError(f"clusters must be >= 2 and divide the {n_res} residuals, got {clusters}")
    blocks = torch.einsum("cnp,cn->cp", jacobian.view(clusters, -1, n_par), residuals.view(clusters, -1))
    active = int((residuals.view(clusters, -1) != 0).any(1).sum())
    cov = bread @ (blocks.T @ blocks * active / max(active - 1, 1)) @ bread
    return 0.5 * (cov + cov.T)


def laplace_samples(jacobian: Tensor, residuals: Tensor, count: int, *, inflation: float = 1.0,
                    generator: torch.Generator | None = None, clusters: int | None = None) -> tuple[Tensor, Tensor]:
    """Draws from ``N(0, inflation² Cov)`` with ``Cov`` the fit's :func:`fit_covariance`.

    Returns:
        (count, P) offsets and the (P, P) covariance (times ``inflation²``).
    """
    cov = inflation**2 * fit_covariance(jacobian, residuals, clusters=clusters)
    values, vectors = torch.linalg.eigh(cov)
    z = torch.randn(count, jacobian.shape[1], dtype=jacobian.dtype, generator=generator)
    return (z * values.clamp(min=0).sqrt()) @ vectors.T, cov


def _predict(problem: Problem, cands: Candidates, n_frames: int, first: int, fps: float) -> tuple[Tensor, Tensor]:
    """Poses of B candidates at every frame from ``first`` on: (B, T, 3, 3), (B, T, 3)."""
    times = torch.arange(0, n_frames - first, dtype=cands.com.dtype) / fps
    with torch.no_grad():
        step = step_size(problem, cands, 2)
        traj = integrate(cands.state(problem.body), times, problem.body, cands.gravity(problem.g), step_size=step)
    return traj.rot, traj.position


def _sizes(params: Tensor) -> dict:
    """Norms of the parts of a (14,) parameter vector, in readable units."""
    return {"rotation_deg": math.degrees(float(params[0:3].norm())), "com_mm": float(1000 * params[3:6].norm()),
            "velocity_m_s": float(params[6:9].norm()), "omega_rad_s": float(params[9:12].norm()),
            "gravity_deg": math.degrees(float(params[12:14].norm()))}


def _horizon(rec, problem: Problem, best: Candidates, drawn: Candidates, horizon: float) -> dict:
    """Rotation error beyond the clip: the fit (and the draws) against the true initial state,
    both simulated by :func:`torchfit.dynamics.integrate` (checked against MuJoCo on the clip)."""
    truth = rec.truth["params"]
    state = torch.tensor([truth["position"] + truth["orientation_wxyz"] + truth["velocity"]
                          + truth["angular_velocity"]], dtype=torch.float64)
    gravity = float(rec.truth["g"]) * torch.tensor(rec.truth["gravity_dir"], dtype=torch.float64)
    fps = float(rec.truth["fps"])
    times = torch.arange(0, round(horizon * fps) + 1, dtype=torch.float64) / fps
    step = 0.25 / max(float(best.omega.norm()), 1.0) / 8  # 1/32 rad per step
    with torch.no_grad():
        true_rot = integrate(state, times, problem.body, gravity, step_size=step).rot[0].numpy()
        fit_rot = integrate(best.state(problem.body), times, problem.body, best.gravity(problem.g),
                            step_size=step).rot
        draw_rot = integrate(drawn.state(problem.body), times, problem.body, drawn.gravity(problem.g),
                             step_size=step).rot
    # the same truth with its spin off by a fixed amount in 16 random directions: how strongly
    # this motion turns a spin error into an orientation error, whatever the fit
    generator = torch.Generator().manual_seed(1)
    directions = torch.randn(16, 3, dtype=torch.float64, generator=generator)
    probes = state.repeat(16, 1)
    probes[:, 10:13] += PROBE_SPIN * directions / directions.norm(dim=-1, keepdim=True)
    with torch.no_grad():
        probe_rot = integrate(probes, times, problem.body, gravity, step_size=step).rot
    clip = len(rec.masks)
    return {"times": times.numpy(),
            "probe": np.median(rotation_error_deg(true_rot, probe_rot, rec.shape.symmetries), axis=0),
            "fit": rotation_error_deg(true_rot, fit_rot[0], rec.shape.symmetries),
            "draws": rotation_error_deg(true_rot, draw_rot, rec.shape.symmetries),
            "integrator_vs_mujoco_deg": float(rotation_error_deg(rec.true_rot(), true_rot[:clip],
                                                                 rec.shape.symmetries).max())}


def _fit_one(name: str, *, quick: bool, window: int, samples: int, inflation: float, crop: int, sigma: float,
             horizon: float, lm_steps: int, device, dtype, progress, seed: int, covariance: str) -> dict:
    from ..run import build_problem, fit_recording  # run.py imports this module

    rec = load_recording(name)
    settings = search_settings(quick, seed)
    clock = time.perf_counter()
    fitted = fit_recording(rec.video, rec.shape, rec.camera, settings, stop=window, g=float(rec.truth["g"]),
                           truth=rec.folder / "truth.json", dtype=dtype, device=device, progress=progress)
    fit_s = time.perf_counter() - clock
    n_frames, first, fps = len(rec.masks), int(fitted.span[0]), fitted.observation.fps
    symmetries = rec.shape.symmetries
    true_rot = rec.true_rot()
    result = fitted.result
    # the best fit and the search's other minima, predicted over the clip
    # the Laplace approximation wants the optimum of the loss it is taken of (float64, crop and
    # sigma below): a few Levenberg-Marquardt steps from the search's answer get there
    problem64, _ = build_problem(fitted.observation, rec.shape, rec.camera, g=float(rec.truth["g"]),
                                 dtype=torch.float64, device=torch.device("cpu"))
    search64 = Candidates(*(getattr(result.candidates, f)[:1].detach().double().cpu()
                            for f in result.candidates.fields()))
    step = step_size(problem64, search64, len(problem64.times))

    def residuals_at(base: Candidates):
        return lambda p: silhouette_residuals(problem64, perturb(base, p[None]), crop=crop, sigma=sigma, step=step)[0]

    clock = time.perf_counter()
    offset, lm_losses = levenberg_marquardt(residuals_at(search64), torch.zeros(N_PARAMS, dtype=torch.float64),
                                            lm_steps)
    best64 = perturb(search64, offset[None]).rebase()
    res, jac = residual_jacobian(residuals_at(best64), torch.zeros(N_PARAMS, dtype=torch.float64))
    jac_s = time.perf_counter() - clock
    progress and progress(f"predict: Levenberg-Marquardt loss {lm_losses[0]:.5f} -> {float(res.square().sum()):.5f}")
    # what is left: the Gauss-Newton step -(JᵀJ)⁻¹ Jᵀ r (small at an optimum)
    newton = -torch.linalg.lstsq(jac, res[:, None]).solution[:, 0]

    def predicted(cands: Candidates, index: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        problem = problem64 if cands.com.dtype == torch.float64 else fitted.problem
        rot, trans = candidate_poses(cands, problem, n_frames, first, fps, index=index)
        masks = hard_silhouettes(fitted.problem, rot[None], trans[None])[0]
        return masks, iou(masks, rec.masks), rotation_error_deg(true_rot, rot, symmetries)

    best_masks, best_iou, best_rot_err = predicted(best64)
    _, search_iou, search_rot_err = predicted(search64)
    refined_score = score_against_truth(str(rec.folder / "truth.json"), as_result(best64, problem64), problem64,
                                       rec.shape, fitted.span)
    alternatives = []
    for k in range(1, len(result.losses)):
        if float(result.losses[k]) > 1.25 * float(result.losses[0]):
            continue
        _, a_iou, a_rot = predicted(result.candidates, k)
        alternatives.append({"loss": float(result.losses[k]), "iou": a_iou, "rotation_error_deg": a_rot})
    generator = torch.Generator().manual_seed(seed)
    frames = len(problem64.times)  # the residuals are per frame: T (crop² + 2)
    offsets, cov = laplace_samples(jac, res, samples, inflation=inflation, generator=generator,
                                   clusters=frames if covariance == "frames" else None)
    other = fit_covariance(jac, res, clusters=None if covariance == "frames" else frames)
    drawn = perturb(best64, offsets)
    s_rot, s_trans = _predict(problem64, drawn, n_frames, first, fps)  # (M, T', 3, 3)
    sample_iou = np.stack([iou(hard_silhouettes(fitted.problem, s_rot[m:m + 1], s_trans[m:m + 1])[0],
                               rec.masks[first:]) for m in range(samples)])  # (M, T')
    sample_rot_err = rotation_error_deg(true_rot[first:], s_rot, symmetries)  # (M, T')
    pad = np.full((samples, first), np.nan)
    sample_iou, sample_rot_err = np.concatenate((pad, sample_iou), 1), np.concatenate((pad, sample_rot_err), 1)
    std = cov.diagonal().sqrt()
    horizon_out = _horizon(rec, problem64, best64, drawn, horizon) if first == 0 else None
    return {
        "horizon": horizon_out, "search_iou": search_iou, "search_rot_err": search_rot_err,
        "refined_truth_score": {k: v for k, v in refined_score.items() if k != "alternatives"},
        "lm_losses": lm_losses,
        "newton_step": _sizes(newton),
        "rec": rec, "fitted": fitted, "first": first, "window": window, "fit_s": fit_s, "jacobian_s": jac_s,
        "best_iou": best_iou, "best_rot_err": best_rot_err, "alternatives": alternatives,
        "sample_iou": sample_iou, "sample_rot_err": sample_rot_err, "best_masks": best_masks,
        "std": _sizes(std), "other_std": _sizes(other.diagonal().clamp(min=0).sqrt()),
        "residual_rms": float(res.square().mean().sqrt()), "loss": float(res.square().sum()),
        "n_residuals": len(res),
    }


def main(out_dir: Path, *, quick: bool = False, device="cpu", dtype=torch.float32, progress=print, seed: int = 0,
         recordings: tuple = ("tshape", "tshape_intermediate"), window: int = 18, samples: int = 48,
         noise_inflation: float = 1.0, crop: int = 64, sigma: float = 0.5, band: tuple = (5, 95),
         horizon: float = 10.0, lm_steps: int = 12, covariance: str = "frames") -> dict:
    """Fit the first ``window`` frames of each recording, predict the rest, plot the errors.

    Args:
        out_dir: folder for the figures and summary.json.
        quick: the small recording, a 7-frame window, 4 samples and the quick search.
        recordings: shipped recordings (major- and intermediate-axis spin by default).
        window: frames fitted (the first ones).
        samples: initial states drawn from the Laplace approximation.
        noise_inflation: multiplies the standard deviations.
        covariance: ``"frames"``: the cluster-robust sandwich with each frame's pixels a cluster
            (neighbouring edge pixels move together); ``"independent"``: ``s² (JᵀJ)⁻¹``, every pixel
            residual independent (see :func:`laplace_samples`).
        crop, sigma: rendering of the residuals (the search's polish uses 64 and 0.5).
        band: percentiles of the plotted spread.
        lm_steps: Levenberg-Marquardt steps from the search's answer to the optimum of the
            float64 loss that the Laplace approximation is taken of (0: none).
        horizon: seconds to extend the rotation prediction past the clip, against the true
            initial state simulated by the same integrator.

    Returns:
        The summary (figures, per-recording errors in and after the window, spreads).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if quick:
        recordings, window, samples, horizon = ("tshape_small",), 7, 4, 1.0
    if window < 6:
        raise ValueError(f"window must be at least 6 frames (14 unknowns), got {window}")
    if covariance not in ("frames", "independent"):
        raise ValueError(f'covariance must be "frames" or "independent", got {covariance!r}')
    if samples < 1 or not noise_inflation > 0:
        raise ValueError(f"samples must be >= 1 and noise_inflation > 0, got {samples}, {noise_inflation}")
    started = time.perf_counter()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda message: None)
    runs = []
    for name in recordings:
        say(f"predict: {name}, fitting frames 0-{window - 1}")
        runs.append(_fit_one(name, quick=quick, window=window, samples=samples, inflation=noise_inflation,
                             crop=crop, sigma=sigma, horizon=horizon, lm_steps=lm_steps, device=device, dtype=dtype,
                             progress=say, seed=seed, covariance=covariance))
    low, high = band
    figures, rows = {}, {}
    fig, axes = plt.subplots(len(runs), 2, figsize=(10, 3.3 * len(runs)), squeeze=False)
    for row, run in zip(axes, runs):
        rec = run["rec"]
        fps = run["fitted"].observation.fps
        times = np.arange(len(rec.masks)) / fps
        spin = rec.truth["spec"]["spin_axis"]
        for ax, key, sample_key, label in ((row[0], "best_iou", "sample_iou", "IoU with the true masks"),
                                           (row[1], "best_rot_err", "sample_rot_err", "rotation error, deg")):
            ax.axvspan(times[run["first"]], times[run["window"] - 1], color="gold", alpha=0.25, label="fitted frames")
            with np.errstate(all="ignore"):
                lo, mid, hi = np.nanpercentile(run[sample_key], [low, 50, high], axis=0)
            ax.fill_between(times, lo, hi, color="C0", alpha=0.3, label=f"{low}-{high}% of {len(run[sample_key])} "
                            "draws from the fit's uncertainty")
            ax.plot(times, mid, "--", color="C0", lw=0.8)
            for alt in run["alternatives"]:
                ax.plot(times, alt["iou" if key == "best_iou" else "rotation_error_deg"], color="gray", lw=0.8,
                        label="another minimum (loss within 25%)")
            ax.plot(times, run["search_iou" if key == "best_iou" else "search_rot_err"], ":", color="k", lw=1,
                    label="search's answer, predicted")
            ax.plot(times, run[key], "k-", lw=1.2, label="after Levenberg-Marquardt, predicted")
            ax.set_xlabel("time, s")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
            ax.set_title(f"{rec.name} (spin about the {spin} axis)", fontsize=9)
        row[1].set_yscale("symlog", linthresh=1.0)
        handles, labels = row[0].get_legend_handles_labels()
        unique = dict(zip(labels, handles))
        row[0].legend(unique.values(), unique.keys(), fontsize=7, loc="lower left")
        after = slice(run["window"], None)
        inside = slice(run["first"], run["window"])
        rows[rec.name] = {
            "spin_axis": spin,
            "frames_fitted": [run["first"], run["window"] - 1],
            "frames_total": len(rec.masks),
            "fit_s": run["fit_s"], "jacobian_s": run["jacobian_s"],
            "search_truth_score": {k: v for k, v in run["fitted"].truth.items() if k != "alternatives"},
            "refined_truth_score": run["refined_truth_score"],
            "lm_losses": run["lm_losses"],
            "search_iou_predicted_mean": float(np.nanmean(run["search_iou"][after])),
            "search_rotation_error_last_frame_deg": float(run["search_rot_err"][-1]),
            "iou_fitted_mean": float(np.nanmean(run["best_iou"][inside])),
            "iou_predicted_mean": float(np.nanmean(run["best_iou"][after])),
            "iou_predicted_min": float(np.nanmin(run["best_iou"][after])),
            "iou_last_frame": float(run["best_iou"][-1]),
            "rotation_error_fitted_max_deg": float(np.nanmax(run["best_rot_err"][inside])),
            "rotation_error_predicted_max_deg": float(np.nanmax(run["best_rot_err"][after])),
            "rotation_error_last_frame_deg": float(run["best_rot_err"][-1]),
            "band_last_frame": {
                "iou": [float(v) for v in np.nanpercentile(run["sample_iou"][:, -1], [low, 50, high])],
                "rotation_error_deg": [float(v) for v in np.nanpercentile(run["sample_rot_err"][:, -1],
                                                                         [low, 50, high])]},
            "laplace_std": run["std"],
            "covariance": covariance,
            ("independent_std" if covariance == "frames" else "frames_std"): run["other_std"],
            "residual_rms": run["residual_rms"], "loss": run["loss"], "n_residuals": run["n_residuals"],
            "alternatives_within_25pct": len(run["alternatives"]),
            "newton_step_at_fit": run["newton_step"],
        }
        if run["horizon"] is not None:
            hz = run["horizon"]
            rows[rec.name]["horizon"] = {
                "seconds": float(hz["times"][-1]),
                "integrator_vs_mujoco_deg": hz["integrator_vs_mujoco_deg"],
                "fit_rotation_error_deg_at": {f"{t:g}s": float(np.interp(t, hz["times"], hz["fit"]))
                                              for t in (0.5, 1.0, 2.0, 5.0, 10.0) if t <= hz["times"][-1] + 1e-9},
                "draws_band_deg_at_end": [float(v) for v in np.percentile(hz["draws"][:, -1], [low, 50, high])],
                "probe_spin_rad_s": PROBE_SPIN,
                "probe_median_error_deg_at": {f"{t:g}s": float(np.interp(t, hz["times"], hz["probe"]))
                                              for t in (0.5, 1.0, 2.0, 5.0, 10.0) if t <= hz["times"][-1] + 1e-9},
            }
    spread = "per-frame sandwich covariance" if covariance == "frames" else "Laplace approximation"
    fig.suptitle(f"fit on the first {runs[0]['window']} frames, predicted to the end; band: {spread}"
                 + (f" (x{noise_inflation:g})" if noise_inflation != 1 else ""), fontsize=9)
    fig.tight_layout()
    figures["prediction"] = "prediction.png"
    fig.savefig(out_dir / figures["prediction"], dpi=110)
    plt.close(fig)

    # beyond the clip: rotation error against the true initial state, same integrator
    extended = [run for run in runs if run["horizon"] is not None]
    if extended:
        fig, ax = plt.subplots(figsize=(7, 3.8))
        for color, run in zip(("C0", "C3", "C2", "C4"), extended):
            hz = run["horizon"]
            lo, hi = np.percentile(hz["draws"], [low, high], axis=0)
            ax.fill_between(hz["times"], np.maximum(lo, 1e-3), hi, color=color, alpha=0.25)
            ax.plot(hz["times"], np.maximum(hz["fit"], 1e-3), color=color,
                    label=f"{run['rec'].name} ({run['rec'].truth['spec']['spin_axis']} axis): fit")
            ax.plot(hz["times"], np.maximum(hz["probe"], 1e-3), "--", color=color, lw=0.9,
                    label=f"truth with spin off by {PROBE_SPIN:g} rad/s (median of 16)")
        ax.axvspan(0, (runs[0]["window"] - 1) / runs[0]["fitted"].observation.fps, color="gold", alpha=0.25,
                   label="fitted frames")
        ax.axvline((len(runs[0]["rec"].masks) - 1) / runs[0]["fitted"].observation.fps, color="k", ls=":", lw=0.8,
                   label="end of the clip")
        ax.set_yscale("log")
        ax.set_xlabel("time, s")
        ax.set_ylabel("rotation error vs truth, deg")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
        ax.set_title(f"prediction past the clip (line: best fit; band: {low}-{high}% of the draws)", fontsize=9)
        fig.tight_layout()
        figures["horizon"] = "horizon.png"
        fig.savefig(out_dir / figures["horizon"], dpi=110)
        plt.close(fig)

    # frames like the paper's: the predicted outline over the true mask, in and after the window
    for run in runs:
        rec = run["rec"]
        from ..video import read_frames

        n_frames = len(rec.masks)
        shown = np.unique(np.linspace(run["first"], n_frames - 1, 7).round().astype(int))
        frames = read_frames(rec.video, shown)
        half = max(16, round(110 * rec.camera.width / 640))
        fig, axes = plt.subplots(1, len(shown), figsize=(2.2 * len(shown), 2.6))
        for ax, image, f in zip(axes, frames, shown):
            ys, xs = np.nonzero(rec.masks[f])
            cu, cv = (0.5 * (xs.min() + xs.max()), 0.5 * (ys.min() + ys.max())) if len(xs) else (0, 0)
            ax.imshow(image)
            ax.contour(run["best_masks"][f].astype(float), [0.5], colors="lime", linewidths=1.0)
            ax.set_xlim(cu - half, cu + half)
            ax.set_ylim(cv + half, cv - half)
            tag = "fitted" if f < run["window"] else "predicted"
            ax.set_title(f"frame {f} ({tag})\nIoU {run['best_iou'][f]:.2f}, {run['best_rot_err'][f]:.1f}°", fontsize=7)
            ax.axis("off")
        fig.suptitle(f"{rec.name}: prediction (green outline) over the video", fontsize=8)
        fig.tight_layout()
        figures[f"frames_{rec.name}"] = f"frames_{rec.name}.png"
        fig.savefig(out_dir / figures[f"frames_{rec.name}"], dpi=110)
        plt.close(fig)

    summary = {"quick": quick, "window": window, "samples": samples, "noise_inflation": noise_inflation,
               "covariance": covariance,
               "band_percentiles": [low, high], "recordings": rows, "figures": figures,
               "total_s": time.perf_counter() - started}
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    say(f"predict: figures in {out_dir}")
    return summary
