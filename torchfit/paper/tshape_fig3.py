"""Paper Fig. 3: a T-shaped object thrown in the air, fitted from its silhouettes.

Row (a) of the paper: the simulation's silhouettes and bounding boxes over the video, and a
corner's trajectory in simulation against the video's. Row (b): the match at stages of the
optimisation. Row (c): an orientation flipped relative to the real one whose silhouettes look
alike. Here the fit needs no initial guess (:func:`torchfit.search.fit`), the truth comes from
the MuJoCo recording, and the flipped orientation is constructed explicitly:

For an object whose mesh has a mirror plane (body reflection ``M``), mirroring the pose through
the plane perpendicular to the viewing ray ``d`` (reflection ``S = I - 2 d dᵀ``) gives the proper
rotation ``R' = S R M``, which projects (orthographically) onto the same silhouette. The torque-
free motion maps along with it: ``R'(t) = S R(t) M`` is again a free rotation, with angular
velocity ``ω' = -S ω`` (a reflection flips a pseudovector), when ``M I M = I``. Perspective
breaks the tie slightly, so the flipped state is refitted locally and its loss compared.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..camera import project
from ..rotation import matrix_to_quat, quat_to_matrix, rotation_angle
from ..search import Candidates, Problem, fit, refine
from ..shape import Shape
from ..video import load_observation, read_frames
from ._recording import (
    box,
    candidate_poses,
    full_loss,
    hard_silhouettes,
    iou,
    load_recording,
    rotation_error_deg,
    search_settings,
)

__all__ = ["corner_track", "flip_candidates", "main", "mirror_planes"]

# a crossbar end's corner of the shipped T-handle mesh (x along the crossbar, y along the stem)
CORNER = (0.1, -0.015, 0.015)


def mirror_planes(shape: Shape, tol: float = 1e-6) -> list[np.ndarray]:
    """Reflections ``M`` (3, 3) about the mesh's coordinate planes through the centre of mass
    that map the mesh onto itself (``M (X - com) + com``) and keep its inertia (``M I M = I``)."""
    vertices = np.asarray(shape.mesh.vertices) - shape.com
    scale = float(np.abs(vertices).max())
    found = []
    for axis in range(3):
        mirror = np.eye(3)
        mirror[axis, axis] = -1.0
        image = vertices @ mirror.T
        gaps = np.linalg.norm(image[:, None] - vertices[None], axis=-1).min(1)
        if gaps.max() <= tol * scale and np.allclose(mirror @ shape.inertia @ mirror, shape.inertia,
                                                     atol=tol * np.abs(shape.inertia).max()):
            found.append(mirror)
    return found


def flip_candidates(cands: Candidates, mirror: Tensor) -> Candidates:
    """The silhouette-preserving flip of each candidate (module docstring).

    Args:
        cands: B candidates (centre-of-mass parametrisation).
        mirror: (3, 3) body reflection ``M`` that maps the shape onto itself.

    Returns:
        B candidates with orientation ``S R M`` and spin ``-S ω``, ``S`` the reflection through
        the plane perpendicular to the viewing ray to each centre of mass; position, velocity
        and gravity unchanged.
    """
    ray = cands.com / cands.com.norm(dim=-1, keepdim=True)  # (B, 3)
    eye = torch.eye(3, dtype=ray.dtype, device=ray.device)
    reflect = eye - 2 * ray[:, :, None] * ray[:, None, :]  # (B, 3, 3)
    rot = reflect @ quat_to_matrix(cands.quat()) @ mirror.to(ray.dtype)
    omega = -(reflect @ cands.omega.unsqueeze(-1)).squeeze(-1)
    return Candidates(matrix_to_quat(rot).detach(), torch.zeros_like(cands.delta), cands.com.detach().clone(),
                      cands.com_velocity.detach().clone(), omega.detach(), cands.gravity_angles.detach().clone())


def corner_track(rot: Tensor, trans: Tensor, corner: Tensor, shape: Shape, symmetry: Tensor) -> Tensor:
    """(T, 3) camera-frame positions of a mesh point under poses (T, 3, 3), (T, 3), with the
    point first moved by the symmetry ``S`` about the centre of mass (to follow the same
    physical corner as a truth that differs from the fit by ``S``)."""
    com = torch.as_tensor(shape.com, dtype=rot.dtype)
    point = symmetry.to(rot.dtype) @ (corner.to(rot.dtype) - com) + com
    return (rot @ point) + trans


def _crop(center: np.ndarray, half: int, width: int, height: int) -> tuple[int, int, int, int]:
    u0 = int(np.clip(round(center[0]) - half, 0, max(width - 2 * half, 0)))
    v0 = int(np.clip(round(center[1]) - half, 0, max(height - 2 * half, 0)))
    return u0, v0, min(u0 + 2 * half, width), min(v0 + 2 * half, height)


def _side_view(rot: Tensor, trans: Tensor, shape: Shape, distance: float) -> tuple[Tensor, Tensor]:
    """Poses seen by a virtual camera 90° around the object's vertical (camera y) axis, looking
    at the centre of mass from ``distance`` metres: (T, 3, 3), (T, 3)."""
    turn = torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype=rot.dtype)
    com = rot @ torch.as_tensor(shape.com, dtype=rot.dtype) + trans  # (T, 3)
    new_rot = turn @ rot
    new_com = torch.tensor([0.0, 0.0, distance], dtype=rot.dtype).expand_as(com)
    return new_rot, new_com - new_rot @ torch.as_tensor(shape.com, dtype=rot.dtype)


def main(out_dir: Path, *, quick: bool = False, device="cpu", dtype=torch.float32, progress=print,
         seed: int = 0, recording: str = "tshape", frames_shown: int = 6, flip_iterations: int = 60) -> dict:
    """Fit the T-handle recording and draw the paper's Fig. 3 rows (a)-(c); write summary.json.

    Args:
        out_dir: folder for the figures and summary.json.
        quick: the small recording and the quick search (seconds; for tests).
        recording: a shipped T-handle recording (``quick`` uses ``tshape_small``).
        frames_shown: frames in the strips.
        flip_iterations: Levenberg–Marquardt iterations (at most) of the flipped candidate's local refit.

    Returns:
        The summary (figures, losses, errors against the truth).
    """
    import matplotlib

    from ..run import build_problem  # run.py imports this module

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    started = time.perf_counter()
    say = progress or (lambda message: None)
    rec = load_recording("tshape_small" if quick else recording)
    if rec.truth.get("shape") != "tshape":
        raise ValueError(f"recording {rec.name!r} is a {rec.truth.get('shape')!r}, not a T-handle (tshape)")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    settings = search_settings(quick, seed)
    observation = load_observation(str(rec.video), camera=rec.camera)
    problem, span = build_problem(observation, rec.shape, rec.camera, g=float(rec.truth["g"]), dtype=dtype,
                                  device=torch.device(device))
    snapshots: list[tuple[str, Candidates, float]] = []

    def keep(stage: str, cands: Candidates, losses: Tensor) -> None:
        best = int(torch.argmin(losses))
        snapshots.append((stage, cands.select(torch.tensor([best])), float(losses[best])))

    clock = time.perf_counter()
    result = fit(problem, settings, progress=say, snapshot=keep)
    fit_s = time.perf_counter() - clock
    say(f"fit: {fit_s:.1f} s, losses {[round(float(v), 5) for v in result.losses]}")

    n_frames, first, fps = len(observation.masks), int(span[0]), observation.fps
    symmetries = torch.as_tensor(rec.shape.symmetries, dtype=torch.float64)
    true_rot, true_pos = rec.true_rot(), rec.true_position()
    rot, trans = candidate_poses(result.candidates, problem, n_frames, first, fps)
    rot, trans = rot.double().cpu(), trans.double().cpu()
    fitted = hard_silhouettes(problem, rot[None], trans[None])[0]
    observed = np.asarray(observation.masks, bool)
    iou_obs, iou_true = iou(fitted, observed), iou(fitted, rec.masks)
    rot_err = rotation_error_deg(true_rot, rot, rec.shape.symmetries)

    # the symmetry element that maps the fit onto the truth at the first fitted frame
    sym_index = int(rotation_angle(torch.as_tensor(true_rot[first]), rot[first] @ symmetries).argmin())
    corner = torch.tensor(CORNER, dtype=torch.float64)
    sim_corner = corner_track(rot, trans, corner, rec.shape, symmetries[sym_index])
    true_corner = torch.as_tensor(true_rot) @ corner + torch.as_tensor(true_pos)
    sim_px = project(rec.camera, sim_corner)[0].numpy()
    true_px = project(rec.camera, true_corner)[0].numpy()
    corner_err_mm = 1000 * (sim_corner - true_corner).norm(dim=-1).numpy()
    corner_err_px = np.linalg.norm(sim_px - true_px, axis=-1)

    frames = read_frames(rec.video, observation.frame_indices)  # (T, H, W, 3)
    width, height = rec.camera.width, rec.camera.height
    half = max(16, round(100 * width / 640))
    shown = np.unique(np.linspace(first, int(span[-1]), frames_shown).round().astype(int))
    fitted_boxes = np.array([box(m) for m in fitted])
    observed_boxes = np.asarray(observation.boxes, float)
    true_boxes = np.array([box(m) for m in rec.masks])
    figures = {}

    # (a) the fit over the video: outline, simulated box, corner trajectories
    fig, axes = plt.subplots(1, len(shown), figsize=(2.4 * len(shown), 2.7))
    for ax, f in zip(np.atleast_1d(axes), shown):
        u0, v0, u1, v1 = _crop(0.5 * (observed_boxes[f, :2] + observed_boxes[f, 2:]), half, width, height)
        ax.imshow(frames[f, v0:v1, u0:u1], extent=(u0 - 0.5, u1 - 0.5, v1 - 0.5, v0 - 0.5))
        ax.contour(np.arange(u0, u1), np.arange(v0, v1), fitted[f, v0:v1, u0:u1].astype(float), [0.5],
                   colors="lime", linewidths=1.0)
        x0, y0, x1, y1 = fitted_boxes[f]
        ax.add_patch(plt.Rectangle((x0 - 0.5, y0 - 0.5), x1 - x0 + 1, y1 - y0 + 1, fill=False, ec="white", lw=1))
        ax.plot(true_px[first:f + 1, 0], true_px[first:f + 1, 1], "s", ms=3, mfc="none", mec="yellow")
        ax.plot(sim_px[first:f + 1, 0], sim_px[first:f + 1, 1], "-", color="cyan", lw=0.8)
        ax.set_xlim(u0 - 0.5, u1 - 0.5)
        ax.set_ylim(v1 - 0.5, v0 - 0.5)
        ax.set_title(f"frame {f}: IoU {iou_obs[f]:.3f}", fontsize=8)
        ax.axis("off")
    fig.suptitle("fit (green outline, white box) over the video; corner: truth (yellow squares), "
                 "simulation (cyan line)", fontsize=8)
    fig.tight_layout()
    figures["fit_strip"] = "fit_strip.png"
    fig.savefig(out_dir / figures["fit_strip"], dpi=110)
    plt.close(fig)

    # (a) bounding boxes: simulated vs observed
    index = np.arange(n_frames)
    fig, axes = plt.subplots(2, 2, figsize=(8, 5), sharex=True)
    for j, (ax, label) in enumerate(zip(axes.ravel(), ("x0", "y0", "x1", "y1"))):
        ax.plot(index, observed_boxes[:, j], "s", ms=4, mfc="none", label="observed (segmented)")
        ax.plot(index, true_boxes[:, j], "+", ms=5, color="gray", label="true mask")
        ax.plot(index, fitted_boxes[:, j], "-", lw=1.2, color="C2", label="simulated (fit)")
        ax.set_ylabel(f"{label}, px")
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("frame")
    axes[0, 0].legend(fontsize=7)
    box_err = np.abs(fitted_boxes - observed_boxes)[first:int(span[-1]) + 1]
    fig.suptitle(f"bounding boxes: |simulated - observed| mean {np.nanmean(box_err):.2f} px, "
                 f"max {np.nanmax(box_err):.1f} px", fontsize=9)
    fig.tight_layout()
    figures["bbox"] = "bbox.png"
    fig.savefig(out_dir / figures["bbox"], dpi=110)
    plt.close(fig)

    # (a) the corner's trajectory
    fig, axes = plt.subplots(3, 1, figsize=(7, 6.5), sharex=True)
    for j, label in enumerate(("u", "v")):
        axes[j].plot(index, true_px[:, j], "s", ms=4, mfc="none", color="C1", label="truth (MuJoCo)")
        axes[j].plot(index, sim_px[:, j], "-", color="k", lw=1, label="simulation (fit)")
        axes[j].set_ylabel(f"corner {label}, px")
        axes[j].grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[2].plot(index, corner_err_mm, "o-", ms=3, label="3-D distance, mm")
    axes[2].plot(index, corner_err_px, "s-", ms=3, label="image distance, px")
    axes[2].set_ylabel("corner error")
    axes[2].set_xlabel("frame")
    axes[2].legend(fontsize=8)
    axes[2].grid(alpha=0.3)
    fig.suptitle(f"crossbar corner {CORNER} m (mesh frame): simulation vs truth", fontsize=9)
    fig.tight_layout()
    figures["corner"] = "corner.png"
    fig.savefig(out_dir / figures["corner"], dpi=110)
    plt.close(fig)

    # (b) stages of the optimisation: each stage's best candidate over all frames (losses at one
    # crop and edge width, so they compare), drawn in the frame the seeds matched worst
    stages, stage_masks = [], []
    used = slice(first, int(span[-1]) + 1)
    for stage, cands, _ in snapshots:
        s_rot, s_trans = candidate_poses(cands, problem, n_frames, first, fps)
        masks = hard_silhouettes(problem, s_rot[None], s_trans[None])[0]
        per_frame = iou(masks, observed)
        stage_masks.append(masks)
        stages.append({"stage": stage, "loss": float(full_loss(problem, cands)[0]),
                       "mean_iou": float(np.nanmean(per_frame[used])), "iou": per_frame})
    stage_frame = first + int(np.nanargmin(stages[0]["iou"][used]))
    fig, axes = plt.subplots(1, len(snapshots) + 1, figsize=(2.3 * (len(snapshots) + 1), 2.9))
    u0, v0, u1, v1 = _crop(0.5 * (observed_boxes[stage_frame, :2] + observed_boxes[stage_frame, 2:]), half,
                           width, height)
    extent = (u0 - 0.5, u1 - 0.5, v1 - 0.5, v0 - 0.5)
    for ax, row, masks in zip(axes[:-1], stages, stage_masks):
        mask = masks[stage_frame, v0:v1, u0:u1]
        ax.imshow(frames[stage_frame, v0:v1, u0:u1], extent=extent)
        ax.imshow(np.ma.masked_where(~mask, mask), cmap="winter", alpha=0.5, extent=extent, vmin=0, vmax=1)
        ax.contour(np.arange(u0, u1), np.arange(v0, v1), observed[stage_frame, v0:v1, u0:u1].astype(float),
                   [0.5], colors="red", linewidths=0.8)
        ax.set_title(f"{row['stage']}: loss {row['loss']:.4f}\nIoU here {row['iou'][stage_frame]:.2f}, "
                     f"mean {row['mean_iou']:.2f}", fontsize=7)
        ax.axis("off")
    for row in stages:
        axes[-1].plot(index, row["iou"], lw=0.9, label=row["stage"])
    axes[-1].axvline(stage_frame, color="k", lw=0.5, ls=":")
    axes[-1].set_xlabel("frame", fontsize=7)
    axes[-1].set_ylabel("IoU", fontsize=7)
    axes[-1].set_title("IoU per frame, each stage", fontsize=7)
    axes[-1].tick_params(labelsize=6)
    axes[-1].legend(fontsize=5)
    fig.suptitle(f"the search's best candidate after each stage, frame {stage_frame} "
                 "(blue: simulated, red outline: observed); losses on all frames, crop 64 px", fontsize=8)
    fig.tight_layout()
    figures["stages"] = "stages.png"
    fig.savefig(out_dir / figures["stages"], dpi=110)
    plt.close(fig)
    for row in stages:
        row["iou"] = [None if math.isnan(v) else float(v) for v in row["iou"]]

    # (c) the flipped orientation
    best = result.candidates.select(torch.tensor([0]))
    mirrors = mirror_planes(rec.shape)
    if not mirrors:
        raise ValueError(f"the mesh of {rec.name!r} has no mirror plane through its centre of mass")
    flipped = flip_candidates(best, torch.as_tensor(mirrors[0], dtype=dtype))
    flip_start_loss = float(full_loss(problem, flipped)[0])
    clock = time.perf_counter()
    refine(problem, flipped, crop=64, sigma=0.5, iterations=flip_iterations)
    flipped = flipped.rebase()
    flip_s = time.perf_counter() - clock
    best_loss, flip_loss = float(full_loss(problem, best)[0]), float(full_loss(problem, flipped)[0])
    f_rot, f_trans = candidate_poses(flipped, problem, n_frames, first, fps)
    f_rot, f_trans = f_rot.double().cpu(), f_trans.double().cpu()
    flip_masks = hard_silhouettes(problem, f_rot[None], f_trans[None])[0]
    flip_iou = iou(flip_masks, observed)
    flip_rot_err = rotation_error_deg(true_rot, f_rot, rec.shape.symmetries)
    flip_vs_best = rotation_error_deg(rot.numpy(), f_rot, rec.shape.symmetries)
    # the search's own distinct minima, and how far each is from the best and from the flip
    alternatives = []
    for k in range(len(result.losses)):
        cand = result.candidates.select(torch.tensor([k]))
        quat = cand.quat().double()
        alternatives.append({
            "loss": float(full_loss(problem, cand)[0]),
            "search_loss": float(result.losses[k]),
            "deg_from_best": float(rotation_error_deg(quat_to_matrix(best.quat().double()).numpy(),
                                                      quat_to_matrix(quat), rec.shape.symmetries)[0]),
            "deg_from_flip": float(rotation_error_deg(quat_to_matrix(flipped.quat().double()).numpy(),
                                                      quat_to_matrix(quat), rec.shape.symmetries)[0]),
            "deg_from_truth": float(rotation_error_deg(true_rot[first:first + 1], quat_to_matrix(quat),
                                                       rec.shape.symmetries)[0]),
        })
    flip_summary = {
        "mirror_used": np.round(mirrors[0], 6).tolist(),
        "loss_at_construction": flip_start_loss,
        "loss_after_refit": flip_loss,
        "best_loss": best_loss,
        "loss_ratio_flip_over_best": flip_loss / best_loss,
        "refit_s": flip_s,
        "mean_iou_best": float(np.nanmean(iou_obs[used])),
        "mean_iou_flip": float(np.nanmean(flip_iou[used])),
        "min_iou_flip": float(np.nanmin(flip_iou[used])),
        "rotation_from_best_deg_t0": float(flip_vs_best[first]),
        "rotation_error_vs_truth_deg_t0": float(flip_rot_err[first]),
        "data_prefers": "best" if best_loss < flip_loss else "flipped",
    }
    # a figure: the same frames from the camera (top rows) and from the side (bottom rows)
    distance = float(np.linalg.norm(true_pos[first]))
    views = [("best fit", rot, trans, "lime"), ("flipped, refitted", f_rot, f_trans, "magenta")]
    cols = np.unique(np.linspace(first, int(span[-1]), 4).round().astype(int))
    fig, axes = plt.subplots(3, len(cols), figsize=(2.5 * len(cols), 7.4))
    for c, f in enumerate(cols):
        u0, v0, u1, v1 = _crop(0.5 * (observed_boxes[f, :2] + observed_boxes[f, 2:]), half, width, height)
        ax = axes[0, c]
        ax.imshow(frames[f, v0:v1, u0:u1], extent=(u0 - 0.5, u1 - 0.5, v1 - 0.5, v0 - 0.5))
        for (label, r, t, color), masks in zip(views, (fitted, flip_masks)):
            ax.contour(np.arange(u0, u1), np.arange(v0, v1), masks[f, v0:v1, u0:u1].astype(float), [0.5],
                       colors=color, linewidths=1.0)
        ax.set_title(f"frame {f}: IoU {iou_obs[f]:.3f} / {flip_iou[f]:.3f}", fontsize=7)
        ax.axis("off")
        side_truth = _side_view(torch.as_tensor(true_rot[f:f + 1]), torch.as_tensor(true_pos[f:f + 1]),
                                rec.shape, distance)
        truth_side = hard_silhouettes(problem, side_truth[0][None].to(rot.dtype), side_truth[1][None])[0, 0]
        for row, (label, r, t, color) in zip((1, 2), views):
            side = _side_view(r[f:f + 1], t[f:f + 1], rec.shape, distance)
            mask = hard_silhouettes(problem, side[0][None], side[1][None])[0, 0]
            ax = axes[row, c]
            ax.imshow(truth_side.astype(float) * 0.35, cmap="gray", vmin=0, vmax=1)
            ax.contour(mask.astype(float), [0.5], colors=color, linewidths=1.0)
            ys, xs = np.nonzero(truth_side | mask)
            if len(xs):
                cu, cv = 0.5 * (xs.min() + xs.max()), 0.5 * (ys.min() + ys.max())
                ax.set_xlim(cu - half, cu + half)
                ax.set_ylim(cv + half, cv - half)
            ax.set_title(f"side view, {label}\n{rotation_error_deg(true_rot[f:f + 1], r[f:f + 1], rec.shape.symmetries)[0]:.0f}° from truth",
                         fontsize=7)
            ax.axis("off")
    fig.suptitle(f"best fit (green, loss {best_loss:.5f}) and its flip (magenta, loss {flip_loss:.5f}): alike "
                 "from the camera, different from the side (grey: truth)", fontsize=8)
    fig.tight_layout()
    figures["flip"] = "flip.png"
    fig.savefig(out_dir / figures["flip"], dpi=110)
    plt.close(fig)

    summary = {
        "recording": rec.name,
        "quick": quick,
        "frames_fitted": [first, int(span[-1])],
        "fit_s": fit_s,
        "total_s": time.perf_counter() - started,
        "search_losses": [float(v) for v in result.losses],
        "truth_score": {k: v for k, v in score_recording(result, problem, rec, span).items()},
        "mean_iou_observed": float(np.nanmean(iou_obs[used])),
        "mean_iou_true_masks": float(np.nanmean(iou_true[used])),
        "min_iou_observed": float(np.nanmin(iou_obs[used])),
        "rotation_error_deg": {"mean": float(rot_err[used].mean()), "max": float(rot_err[used].max())},
        "corner_error_mm": {"mean": float(corner_err_mm[used].mean()), "max": float(corner_err_mm[used].max())},
        "corner_error_px": {"mean": float(corner_err_px[used].mean()), "max": float(corner_err_px[used].max())},
        "bbox_error_px": {"mean": float(np.nanmean(box_err)), "max": float(np.nanmax(box_err))},
        "stages_frame": stage_frame,
        "stages": stages,
        "flip": flip_summary,
        "alternatives": alternatives,
        "figures": figures,
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    say(f"tshape_fig3: loss {best_loss:.5f}, flipped {flip_loss:.5f}; figures in {out_dir}")
    return summary


def score_recording(result, problem: Problem, rec, span) -> dict:
    """:func:`torchfit.report.score_against_truth` without the per-candidate rows."""
    from ..report import score_against_truth

    score = score_against_truth(str(rec.folder / "truth.json"), result, problem, rec.shape, span)
    return {k: v for k, v in score.items() if k != "alternatives"}
