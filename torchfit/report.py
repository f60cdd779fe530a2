"""Outputs of a run: result.json (DESIGN.md's contract), the overlay video, plots, a summary.

Also scores a fit against a ground-truth file (the MuJoCo recordings'), so that every run on a
recording with known truth says how right it was.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from .camera import Camera, tilt_roll_from_direction
from .dynamics import integrate
from .provenance import provenance
from .render import full_window, render_silhouettes
from .rotation import matrix_to_quat, quat_to_matrix, rotation_angle
from .search import FitResult, Problem
from .shape import Shape
from .video import camera_motion_fields

__all__ = ["simulate_recording", "write_outputs", "score_against_truth", "summary_text", "params_dict"]


def params_dict(state: torch.Tensor, gravity: torch.Tensor) -> dict:
    """DESIGN.md's ``params`` from one (13,) user-convention state and a (3,) gravity vector."""
    state = state.detach().double().cpu()
    direction = gravity.detach().double().cpu()
    direction = direction / direction.norm()
    tilt, roll = tilt_roll_from_direction(direction)
    rot = quat_to_matrix(state[3:7])
    return {
        "position": state[0:3].tolist(),
        "orientation_wxyz": matrix_to_quat(rot).tolist(),
        "R": rot.tolist(),
        "velocity": state[7:10].tolist(),
        "angular_velocity": state[10:13].tolist(),
        "gravity_dir": direction.tolist(),
        "tilt_deg": math.degrees(float(tilt)),
        "roll_deg": math.degrees(float(roll)),
    }


def simulate_recording(result: FitResult, problem: Problem, n_frames: int, first: int, fps: float,
                       index: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Poses of candidate ``index`` at every frame of the recording (before the fitted span too).

    Returns:
        rot: (n_frames, 3, 3); trans: (n_frames, 3).
    """
    state = result.state[index:index + 1]
    gravity = result.candidates.gravity(problem.g)[index:index + 1]
    dtype = state.dtype
    rots, trans = [], []
    if first > 0:  # integrate backwards from t = 0 to the frames before the span
        back = -torch.arange(0, first + 1, dtype=dtype, device=state.device) / fps
        traj = integrate(state, back, problem.body, gravity)
        rots.append(traj.rot[0, 1:].flip(0))
        trans.append(traj.position[0, 1:].flip(0))
    fwd = torch.arange(0, n_frames - first, dtype=dtype, device=state.device) / fps
    traj = integrate(state, fwd, problem.body, gravity)
    rots.append(traj.rot[0])
    trans.append(traj.position[0])
    return torch.cat(rots), torch.cat(trans)


def _box(mask: np.ndarray) -> list[float] | None:
    ys, xs = np.nonzero(mask)
    return None if len(xs) == 0 else [float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())]


def write_outputs(out_dir: Path, result: FitResult, problem: Problem, observation, shape: Shape,
                  camera: Camera, span: np.ndarray, timing: dict, truth: dict | None, *,
                  overlay: bool = True, plots: bool = True) -> dict:
    """Write result.json, the overlay video and the plots; return result.json's content."""
    n_frames = len(observation.masks)
    first = int(span[0])
    with torch.no_grad():
        rot, trans = simulate_recording(result, problem, n_frames, first, observation.fps)
        fitted = render_silhouettes(problem.mesh, camera, rot[None], trans[None],
                                    full_window(camera, 1, n_frames, dtype=rot.dtype, device=rot.device),
                                    size=(camera.height, camera.width), sigma=None)[0].cpu().numpy() > 0.5
    observed = np.asarray(observation.masks, bool)
    inter = (fitted & observed).sum((1, 2))
    union = (fitted | observed).sum((1, 2))
    iou = np.where(union > 0, inter / np.maximum(union, 1), np.nan)
    used = np.asarray(observation.used, bool)
    per_frame = {
        "frame": [int(f) for f in observation.frame_indices],
        "time": [float((i - first) / observation.fps) for i in range(n_frames)],
        "R": rot.double().cpu().tolist(),
        "position": trans.double().cpu().tolist(),
        "iou": [None if math.isnan(v) else float(v) for v in iou],
        "observed_bbox": [_box(m) for m in observed],
        "fitted_bbox": [_box(m) for m in fitted],
        "used": used.tolist(),
        "reason": list(observation.reasons),
    }
    candidates = []
    gravity = result.candidates.gravity(problem.g)
    for k in range(len(result.losses)):
        candidates.append({"params": params_dict(result.state[k], gravity[k]), "loss": float(result.losses[k])})
    content = {
        "params": candidates[0]["params"],
        "loss": candidates[0]["loss"],
        "mean_iou": float(np.nanmean(iou[used])) if used.any() else None,
        "per_frame": per_frame,
        "candidates": candidates,
        "shape": {"name": shape.name, "mass": shape.mass, "com": shape.com.tolist(),
                  "inertia": shape.inertia.tolist(), "symmetry_order": len(shape.symmetries)},
        "camera": {k: getattr(camera, k) for k in ("fx", "fy", "cx", "cy", "width", "height")},
        "fps": observation.fps,
        "source": str(observation.source),
        **camera_motion_fields(observation),
        "provenance": provenance(observation.source, observed),
        "stages": [{"stage": name, "seconds": sec, "best_loss": (None if math.isnan(loss) else loss),
                    "candidates": count} for name, sec, loss, count in result.history],
        "track": {k: (v.tolist() if torch.is_tensor(v) else v) for k, v in result.track.items()},
        "timing": timing,
    }
    if truth is not None:
        content["truth"] = truth
    (out_dir / "result.json").write_text(json.dumps(content, indent=1))
    if plots:
        _plots(out_dir, per_frame, result.loss_curve)
    if overlay:
        _overlay_video(out_dir / "overlay.mp4", observation, fitted)
    return content


def _plots(out_dir: Path, per_frame: dict, curve: list) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = np.asarray(per_frame["frame"])
    iou = np.array([np.nan if v is None else v for v in per_frame["iou"]])
    used = np.asarray(per_frame["used"])
    fig, axes = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    axes[0].plot(frames, iou, "o-", ms=3, label="IoU (fitted vs observed)")
    axes[0].plot(frames[~used], iou[~used], "x", color="red", label="left out of the fit")
    axes[0].set_ylabel("IoU")
    axes[0].set_ylim(min(0.5, np.nanmin(iou) if np.isfinite(iou).any() else 0.5), 1.0)
    axes[0].legend(loc="lower left")
    axes[0].grid(alpha=0.3)
    obs = [b for b in per_frame["observed_bbox"]]
    fit = [b for b in per_frame["fitted_bbox"]]
    for j, label in ((0, "x"), (1, "y")):
        co = [np.nan if b is None else 0.5 * (b[j] + b[j + 2]) for b in obs]
        cf = [np.nan if b is None else 0.5 * (b[j] + b[j + 2]) for b in fit]
        axes[1].plot(frames, np.asarray(cf) - np.asarray(co), "o-", ms=3, label=f"box centre {label}")
    axes[1].axhline(0, color="k", lw=0.5)
    axes[1].set_ylabel("fitted − observed, px")
    axes[1].set_xlabel("frame")
    axes[1].legend(loc="lower left")
    axes[1].grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out_dir / "iou.png", dpi=110)
    plt.close(fig)
    if curve:
        fig, ax = plt.subplots(figsize=(6, 3.5))
        ax.semilogy(curve)
        ax.set_xlabel("optimiser step (Adam stages, then Levenberg–Marquardt iterations)")
        ax.set_ylabel("best loss")
        ax.set_title("jumps where a stage adds frames or pixels", fontsize=9)
        ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(out_dir / "loss.png", dpi=110)
        plt.close(fig)


def _overlay_video(path: Path, observation, fitted: np.ndarray) -> None:
    import cv2

    from .video import observed_frames

    try:
        frames = observed_frames(observation)  # (T, H, W, 3) RGB, as segmented (moved back if stabilised)
    except Exception:  # noqa: BLE001 - masks input has no frames: draw on black
        frames = np.zeros((*fitted.shape, 3), np.uint8)
    height, width = fitted.shape[1:]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(observation.fps), (width, height))
    for frame, fit_mask, obs_mask, used in zip(frames, fitted, observation.masks, observation.used):
        image = cv2.cvtColor(frame, cv2.COLOR_RGB2BGR)
        tint = image.copy()
        tint[fit_mask] = (0.5 * tint[fit_mask] + (0, 127, 0)).astype(np.uint8)
        image = tint
        contours, _ = cv2.findContours(obs_mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(image, contours, -1, (0, 0, 255) if used else (0, 128, 255), 1)
        writer.write(image)
    writer.release()


def score_against_truth(truth_path: str, result: FitResult, problem: Problem, shape: Shape,
                        span: np.ndarray) -> dict:
    """Errors of the best fit (and whether the truth is among the alternatives) at time 0.

    Success as in experiments/fit/README.md: rotation error ≤ 5° modulo symmetry (or the truth
    among the alternatives with loss within noise of the best), position error ≤ 2% of depth,
    gravity direction ≤ 2°.
    """
    truth = json.loads(Path(truth_path).read_text())
    frame = int(span[0])
    pf = truth["per_frame"]
    true_rot = torch.tensor(pf["R"][frame], dtype=torch.float64)
    true_pos = torch.tensor(pf["position"][frame], dtype=torch.float64)
    true_dir = torch.tensor(truth["gravity_dir"], dtype=torch.float64)
    symmetries = torch.as_tensor(shape.symmetries, dtype=torch.float64)
    states = result.state.detach().double().cpu()
    gravity = result.candidates.gravity(problem.g).detach().double().cpu()
    rows = []
    for k in range(len(states)):
        rot = quat_to_matrix(states[k, 3:7])
        rows.append({
            "rotation_error_deg": math.degrees(float(rotation_angle(true_rot, rot @ symmetries).min())),
            "position_error_m": float((states[k, 0:3] - true_pos).norm()),
            "gravity_error_deg": math.degrees(float(torch.acos((gravity[k] / gravity[k].norm() @ true_dir).clamp(-1, 1)))),
        })
    out = dict(rows[0])
    depth = float(true_pos[2])
    out["position_error_pct_depth"] = 100 * out["position_error_m"] / depth
    if frame == 0 and "angular_velocity" in truth.get("params", {}):
        true_omega = torch.tensor(truth["params"]["angular_velocity"], dtype=torch.float64)
        out["angular_velocity_error"] = float((states[0, 10:13] - true_omega).norm())
        out["angular_velocity_true_norm"] = float(true_omega.norm())
    losses = result.losses.double().cpu()
    near = [k for k in range(len(rows)) if float(losses[k]) <= 1.25 * float(losses[0])]
    out["truth_among_alternatives"] = any(rows[k]["rotation_error_deg"] <= 5.0 for k in near)
    out["alternatives"] = rows
    ok_rot = out["rotation_error_deg"] <= 5.0 or out["truth_among_alternatives"]
    out["success"] = bool(ok_rot and out["position_error_pct_depth"] <= 2.0 and out["gravity_error_deg"] <= 2.0)
    return out


def summary_text(content: dict, out_dir: Path) -> str:
    """A few lines a person reads at the end of a run."""
    p = content["params"]
    lines = [
        f"torchfit: fitted {sum(content['per_frame']['used'])} frames of {content['source']}",
        f"  position {np.round(p['position'], 4).tolist()} m, velocity {np.round(p['velocity'], 3).tolist()} m/s",
        f"  orientation (wxyz) {np.round(p['orientation_wxyz'], 4).tolist()}, "
        f"spin {np.round(p['angular_velocity'], 2).tolist()} rad/s",
        f"  gravity: tilt {p['tilt_deg']:.2f}°, roll {p['roll_deg']:.2f}°; loss {content['loss']:.5f}, "
        f"mean IoU {content['mean_iou']:.3f}",
        f"  {len(content['candidates'])} distinct candidates; losses "
        + ", ".join(f"{c['loss']:.4f}" for c in content["candidates"]),
        f"  time {content['timing'].get('total_s', float('nan')):.1f} s",
    ]
    truth = content.get("truth")
    if truth:
        lines.append(
            f"  vs truth: rotation {truth['rotation_error_deg']:.2f}° (mod symmetry), position "
            f"{1000 * truth['position_error_m']:.1f} mm ({truth['position_error_pct_depth']:.2f}% of depth), "
            f"gravity {truth['gravity_error_deg']:.2f}°"
            + (f", spin {truth['angular_velocity_error']:.2f} rad/s" if "angular_velocity_error" in truth else "")
            + f"; success: {truth['success']}")
    lines.append(f"  outputs in {out_dir}")
    return "\n".join(lines)
