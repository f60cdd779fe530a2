"""Convergence basin: the paper's gradient descent from perturbed truths vs. torchfit from nothing.

On each recording, the paper's method (:func:`torchfit.paper.method.paper_fit`: hard
silhouettes, hybrid gradient, plain gradient descent) starts from the true initial state with the
orientation turned by 0°, 15°, 30°, 60°, 90° or 180° about a random axis and the angular
velocity moved by ``|ω| · angle / 180°`` in a random direction; position, velocity and gravity
start at the truth. The same axes and directions are used at every level, so the level is the
only thing that changes. torchfit's search (:func:`torchfit.search.fit`, default settings) runs
once per recording with no guess. Both are scored by
:func:`torchfit.report.score_against_truth` on the same segmented recording, and both are timed
on the same machine in the same run.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from ..dynamics import RigidBody, integrate
from ..report import score_against_truth
from ..rotation import axis_angle_to_quat, quat_multiply
from ..search import SearchSettings, fit
from ..video import load_observation
from ._recording import load_recording
from .method import PaperSettings, paper_fit

__all__ = ["QUICK_SEARCH", "main"]


# a very small search for the quick mode (tests): torchfit/configs/search/quick.yaml, shrunk
QUICK_SEARCH = {"orientations": 200, "keep_per_anchor": 4, "anchor_steps": 6, "seed_frames": 6, "survivors": 6,
                "stages": ((1.0, 24, 1.0, 8, 1.0),), "final": 2, "polish_iterations": 4, "polish_crop": 32,
                "polish_sigma": 0.8}


def _truth_at(truth: dict, problem, span: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The true (13,) state at the problem's time 0 (frame ``span[0]``) and the gravity direction."""
    params = truth["params"]
    state = torch.tensor(params["position"] + params["orientation_wxyz"] + params["velocity"]
                         + params["angular_velocity"], dtype=torch.float64)
    direction = torch.tensor(truth["gravity_dir"], dtype=torch.float64)
    first = int(span[0])
    if first > 0:  # carry the truth forward to the first fitted frame with our integrator
        body = RigidBody(problem.body.mass.double().cpu(), problem.body.com.double().cpu(),
                         problem.body.inertia.double().cpu())
        times = torch.tensor([0.0, first / float(truth["fps"])], dtype=torch.float64)
        traj = integrate(state[None], times, body, float(truth["g"]) * direction, step_size=1e-3)
        state = traj.states[0, -1]
    return state, direction


def _perturb(state: torch.Tensor, angle_deg: float, axis: np.ndarray, spin_dir: np.ndarray) -> torch.Tensor:
    """Turn the orientation by ``angle_deg`` about ``axis`` (camera frame) and move the spin by
    ``|ω| angle / 180°`` along ``spin_dir``."""
    out = state.clone()
    angle = math.radians(angle_deg)
    turn = axis_angle_to_quat(torch.as_tensor(axis * angle, dtype=state.dtype))
    out[3:7] = quat_multiply(turn, state[3:7])
    out[10:13] = state[10:13] + state[10:13].norm() * (angle_deg / 180.0) * torch.as_tensor(spin_dir, dtype=state.dtype)
    return out


def _unit(rng: np.random.Generator) -> np.ndarray:
    vector = rng.normal(size=3)
    return vector / np.linalg.norm(vector)


def _median(values: list) -> float:
    return float(statistics.median(values)) if values else float("nan")


def main(out_dir: Path, *, quick: bool = False, device="cpu", dtype=torch.float32, progress=print, seed: int = 0,
         recordings: tuple = ("tshape", "tshape_intermediate", "box_fast"),
         levels_deg: tuple = (0, 15, 30, 60, 90, 180), axes: int = 2, iterations: int = 40, step: float = 0.1,
         crop: int = 48, fd_steps: tuple = PaperSettings.fd_steps) -> dict:
    """Run the comparison; write ``basin.png`` and ``summary.json`` into ``out_dir``.

    Args:
        quick: a seconds-long smoke run (``tshape_small``, levels 0° and 15°, one axis, a few
            iterations, a tiny search).
        recordings: shipped recordings to use.
        levels_deg: orientation perturbations, degrees.
        axes: random perturbation directions per recording (the same at every level).
        iterations, step, crop, fd_steps: the paper method's :class:`PaperSettings`.

    Returns:
        The summary: per-trial rows, per-level success rates and median wall times, torchfit's
        rows, and whether the target (torchfit from nothing at least as successful as the paper
        from 15°, in less wall time) holds.
    """
    from ..run import build_problem  # run.py imports this module

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda message: None)
    if quick:
        recordings, levels_deg, axes, iterations = ("tshape_small",), (0, 15), 1, 4
        search = SearchSettings(**QUICK_SEARCH, seed=seed)
    else:
        search = SearchSettings(seed=seed)
    levels_deg = tuple(float(level) for level in levels_deg)
    if int(axes) < 1:
        raise ValueError(f"axes must be at least 1, got {axes}")
    settings = PaperSettings(iterations=int(iterations), step=float(step), crop=int(crop), fd_steps=tuple(fd_steps))
    rng = np.random.default_rng(seed)
    trials, torchfit_rows = [], []
    for name in recordings:
        rec = load_recording(name)
        truth_path, truth, shape, camera = rec.folder / "truth.json", rec.truth, rec.shape, rec.camera
        observation = load_observation(str(rec.video), camera=camera)
        problem, span = build_problem(observation, shape, camera, g=float(truth["g"]), dtype=dtype,
                                      device=torch.device(device))
        say(f"{name}: torchfit from no guess ({len(span)} frames)")
        clock, cpu_clock = time.perf_counter(), time.process_time()
        result = fit(problem, search, progress=say)
        wall, cpu = time.perf_counter() - clock, time.process_time() - cpu_clock
        score = score_against_truth(str(truth_path), result, problem, shape, span)
        torchfit_rows.append({"recording": name, "success": bool(score["success"]),
                              "rotation_error_deg": score["rotation_error_deg"],
                              "position_error_pct_depth": score["position_error_pct_depth"],
                              "gravity_error_deg": score["gravity_error_deg"],
                              "loss": float(result.losses[0]), "wall_s": wall, "cpu_s": cpu})
        say(f"{name}: torchfit success {score['success']}, rotation error {score['rotation_error_deg']:.2f}°, "
            f"{wall:.1f} s wall, {cpu:.1f} s cpu")
        true_state, true_dir = _truth_at(truth, problem, span)
        directions = [(_unit(rng), _unit(rng)) for _ in range(int(axes))]
        for level in levels_deg:
            for index, (axis, spin_dir) in enumerate(directions):
                guess = _perturb(true_state, level, axis, spin_dir)
                result = paper_fit(problem, guess.to(dtype), true_dir.to(dtype), settings)
                score = score_against_truth(str(truth_path), result.as_fit_result(), problem, shape, span)
                trials.append({"recording": name, "level_deg": level, "axis": index, "success": bool(score["success"]),
                               "rotation_error_deg": score["rotation_error_deg"],
                               "position_error_pct_depth": score["position_error_pct_depth"],
                               "gravity_error_deg": score["gravity_error_deg"],
                               "initial_loss": result.loss_curve[0], "loss": result.loss,
                               "iterations": result.iterations, "evaluations": result.evaluations,
                               "wall_s": result.seconds, "cpu_s": result.cpu_seconds})
                say(f"{name}: paper from {level:g}° (axis {index}): success {score['success']}, rotation error "
                    f"{score['rotation_error_deg']:.2f}°, loss {result.loss_curve[0]:.4f} -> {result.loss:.4f}, "
                    f"{result.iterations} iterations, {result.seconds:.1f} s wall, {result.cpu_seconds:.1f} s cpu")

    levels = []
    for level in levels_deg:
        rows = [t for t in trials if t["level_deg"] == level]
        levels.append({"level_deg": level, "trials": len(rows), "successes": sum(t["success"] for t in rows),
                       "success_rate": sum(t["success"] for t in rows) / len(rows),
                       "median_wall_s": _median([t["wall_s"] for t in rows]),
                       "median_cpu_s": _median([t["cpu_s"] for t in rows]),
                       "median_rotation_error_deg": _median([t["rotation_error_deg"] for t in rows])})
    torchfit = {"trials": len(torchfit_rows), "successes": sum(r["success"] for r in torchfit_rows),
                "success_rate": sum(r["success"] for r in torchfit_rows) / len(torchfit_rows),
                "median_wall_s": _median([r["wall_s"] for r in torchfit_rows]),
                "median_cpu_s": _median([r["cpu_s"] for r in torchfit_rows]),
                "median_rotation_error_deg": _median([r["rotation_error_deg"] for r in torchfit_rows])}
    reference = next((row for row in levels if row["level_deg"] == 15.0), None)
    target = None
    if reference is not None:
        target = {"success_at_least_paper_15deg": torchfit["success_rate"] >= reference["success_rate"],
                  "faster_than_paper_15deg": torchfit["median_wall_s"] < reference["median_wall_s"]}
        target["less_cpu_than_paper_15deg"] = torchfit["median_cpu_s"] < reference["median_cpu_s"]
        target["holds"] = target["success_at_least_paper_15deg"] and target["faster_than_paper_15deg"]
    _figure(out_dir / "basin.png", levels, torchfit)
    summary = {"recordings": list(recordings), "levels": levels, "torchfit": torchfit, "target": target,
               "paper_settings": {"iterations": settings.iterations, "step": settings.step, "grow": settings.grow,
                                  "max_backtracks": settings.max_backtracks, "min_step": settings.min_step,
                                  "fd_steps": list(settings.fd_steps), "crop": settings.crop},
               "axes_per_recording": int(axes), "seed": int(seed), "quick": bool(quick),
               "torch_threads": torch.get_num_threads(), "table": _table(levels, torchfit),
               "torchfit_runs": torchfit_rows, "trials": trials, "figure": "basin.png"}
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    say("\n" + summary["table"])
    return summary


def _table(levels: list, torchfit: dict) -> str:
    lines = ["| start | trials | success | median wall time (s) | median CPU time (s) | median rotation error (°) |",
             "|---|---|---|---|---|---|"]
    for row in levels:
        lines.append(f"| paper, truth turned {row['level_deg']:g}° | {row['trials']} | {row['successes']}/{row['trials']} "
                     f"({100 * row['success_rate']:.0f} %) | {row['median_wall_s']:.1f} | {row['median_cpu_s']:.1f} | "
                     f"{row['median_rotation_error_deg']:.2f} |")
    lines.append(f"| torchfit, no guess | {torchfit['trials']} | {torchfit['successes']}/{torchfit['trials']} "
                 f"({100 * torchfit['success_rate']:.0f} %) | {torchfit['median_wall_s']:.1f} | {torchfit['median_cpu_s']:.1f} | "
                 f"{torchfit['median_rotation_error_deg']:.2f} |")
    return "\n".join(lines)


def _figure(path: Path, levels: list, torchfit: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    angles = [row["level_deg"] for row in levels]
    rates = [100 * row["success_rate"] for row in levels]
    fig, ax = plt.subplots(figsize=(6.4, 4.6))
    ax.plot(angles, rates, "o-", color="tab:red", label="paper's method from the truth turned by x")
    for angle, rate, row in zip(angles, rates, levels):
        ax.annotate(f"{row['median_wall_s']:.0f} s / {row['median_cpu_s']:.0f} s", (angle, rate), textcoords="offset points", xytext=(4, 6),
                    fontsize=8, color="tab:red")
    rate = 100 * torchfit["success_rate"]
    ax.axhline(rate, color="tab:blue", ls="--",
               label=f"torchfit from no guess ({torchfit['successes']}/{torchfit['trials']}, "
                     f"median {torchfit['median_wall_s']:.0f} s / {torchfit['median_cpu_s']:.0f} s)")
    ax.set_xlabel("orientation perturbation of the start (°); spin moved by |ω|·x/180°")
    ax.set_ylabel("success rate (%)")
    ax.set_ylim(-5, 110)
    ax.set_xticks(angles)
    ax.set_title("Convergence basin (labels: median wall / CPU time per fit)", fontsize=10)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=1, frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
