"""Discover air drag and Magnus lift in real table-tennis flights (SpinDOE, Gossard et al. 2023).

    OMP_NUM_THREADS=1 python experiments/discover/spindoe.py   # ~5-10 min on one core

Data: /work/shared/data/spindoe/trajectories.zip — 232 measured trajectories with each ball's
spin (T. Gossard, J. Tebbe, A. Ziegler, A. Zell, "SpinDOE: A ball spin estimation method for table
tennis robot", arXiv 2303.03879, 2023). Each trajectory is cut at its impacts (table bounce, net);
the piece before the first impact is the flight the spin belongs to.

Writes into experiments/discover/results/: pre_bounce/discover.json + residuals.png (discover with
the measured spin, effect parameters shared by all balls), rms_steps.png, lift.png, summary.json.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch

from torchfit.discover import PointsProblem, SelectionSettings, discover_points
from torchfit.points import (
    POINT_EFFECTS,
    PointData,
    PointModel,
    batch_tracks,
    fit_tracks,
    load_spindoe,
)

DATA = Path("/work/shared/data/spindoe/trajectories.zip")
RADIUS, MASS = 0.02, 0.0027
BALL = {"area": math.pi * RADIUS ** 2, "mass": MASS, "moment": 2 / 3 * MASS * RADIUS ** 2}  # thin shell


def per_track(data: PointData, effects, start_from) -> tuple[torch.Tensor, torch.Tensor, PointModel]:
    """Each ball its own effect parameters: (B, E) values and (B, E) standard errors."""
    problem = PointsProblem(data, candidates=(), **BALL)
    model = problem.model(effects)
    values = start_from.model.unpack(start_from.params)
    fit = fit_tracks(model, data, model.pack(values, data.batch), shared=False)
    n = data.weights.sum(-1)
    per_var = (fit.residual ** 2 * data.weights.unsqueeze(-1)).sum((1, 2)) / (3 * n - model.n_params).clamp(min=1)
    std = torch.sqrt(torch.diagonal(fit.covariance, dim1=1, dim2=2)[:, model.n_local:] * per_var.unsqueeze(-1))
    return fit.params[:, model.n_local:], std, model


def spin_consistency(data: PointData, drag_fit) -> dict:
    """Fit each ball's spin from its flight (Magnus with C_L = 1, spin free per track) and compare
    its direction across the flight with the measured spin's."""
    free = PointData(data.times, data.positions, data.weights, None, data.names)
    problem = PointsProblem(free, candidates=(), **BALL)
    model = problem.model(["quadratic_drag", "magnus"])
    values = drag_fit.model.unpack(drag_fit.params)
    values[("magnus", "spin")] = data.spin * 0.3
    fit = fit_tracks(model, free, model.pack(values, data.batch), shared=True)
    v = fit.params[:, 3:6]
    along = v / v.norm(dim=-1, keepdim=True)
    across = lambda w: w - (w * along).sum(-1, keepdim=True) * along
    fitted, measured = across(fit.params[:, 6:9]), across(data.spin)
    cosine = (fitted * measured).sum(-1) / (fitted.norm(dim=-1) * measured.norm(dim=-1)).clamp(min=1e-9)
    ratio = (fitted * measured).sum(-1) / (measured * measured).sum(-1)
    return {"cosine": cosine, "ratio": ratio, "rms_m": math.sqrt(fit.rss / fit.n_obs), "fit": fit}


def main(out_dir: Path, limit: int | None = None, backcast: bool = False) -> dict:
    """Both discover runs (all pre-bounce flights, then those whose measured spin agrees with their
    flight) and the follow-ups; ``backcast``: each flight's first quarter held out as well
    (:class:`torchfit.discover.PointsProblem`)."""
    clock = time.perf_counter()
    tracks = load_spindoe(DATA, pieces=(0,), limit=limit)
    data = batch_tracks(tracks)
    say = lambda message: print(message, flush=True)
    say(f"{len(tracks)} pre-bounce flights from {len({t.meta['trajectory'] for t in tracks})} trajectories, "
        f"{int(data.weights.sum())} samples")
    settings = SelectionSettings()
    content = discover_points(data, candidates=POINT_EFFECTS, settings=settings, out_dir=out_dir / "pre_bounce",
                              progress=say, backcast=backcast, **BALL)
    problem = PointsProblem(data, candidates=(), backcast=backcast, **BALL)  # the same fits, for the follow-ups
    drag_only = problem.fit(("quadratic_drag",), problem.fit((), None))
    both = problem.fit(("quadratic_drag", "magnus"), drag_only)

    # per-ball coefficients: the spread over balls is the honest uncertainty
    per_values, _, _ = per_track(data, ["quadratic_drag", "magnus"], both.payload["all"])
    cd, cl = per_values[:, 0].numpy(), per_values[:, 1].numpy()
    speed = both.payload["all"].params[:, 3:6].norm(dim=-1)
    v_hat = both.payload["all"].params[:, 3:6] / speed.unsqueeze(-1)
    spin_across = (data.spin - (data.spin * v_hat).sum(-1, keepdim=True) * v_hat).norm(dim=-1)
    spin_ratio = (RADIUS * spin_across / speed).numpy()

    consistency = spin_consistency(data, drag_only.payload["all"])
    agree = (consistency["cosine"] > 0.5).numpy()
    subset = PointData(data.times[agree], data.positions[agree], data.weights[agree], data.spin[agree],
                       tuple(n for n, a in zip(data.names, agree) if a))
    say(f"discover again on the {int(agree.sum())} flights whose measured spin agrees with their flight")
    sub_content = discover_points(subset, candidates=POINT_EFFECTS, settings=settings, out_dir=out_dir / "agreeing",
                                  progress=say, backcast=backcast, **BALL)
    sub_problem = PointsProblem(subset, candidates=(), backcast=backcast, **BALL)
    sub_drag = sub_problem.fit(("quadratic_drag",), sub_problem.fit((), None))
    sub_both = sub_problem.fit(("quadratic_drag", "magnus"), sub_drag)

    def robust(values: np.ndarray) -> dict:
        q1, med, q3 = np.percentile(values, [25, 50, 75])
        return {"median": float(med), "iqr": [float(q1), float(q3)], "mean": float(values.mean()),
                "sem": float(values.std(ddof=1) / math.sqrt(len(values))),
                "median_se": float(1.2533 * values.std(ddof=1) / math.sqrt(len(values)))}

    def row(fit):
        return {"effects": list(fit.effects), "rms_mm": 1e3 * fit.fit_rms, "heldout_rms_mm": 1e3 * fit.heldout_rms,
                "heldout_track_median_mm": 1e3 * fit.heldout_track_median}

    summary = {
        "data": {"flights": len(tracks), "samples": int(data.weights.sum()), "noise_rms_mm": 1e3 * content["noise_rms_m"],
                 "speed_m_s": np.percentile(speed.numpy(), [10, 50, 90]).tolist(),
                 "spin_rad_s": np.percentile(data.spin.norm(dim=-1).numpy(), [10, 50, 90]).tolist(),
                 "spin_ratio_across": np.percentile(spin_ratio, [10, 50, 90]).tolist()},
        "verdict": content["verdict"],
        "indistinguishable": content["indistinguishable"],
        "steps": [{"effects": m["effects"], "rms_mm": 1e3 * m["rms_m"], "heldout_rms_mm": 1e3 * m["heldout_rms_m"],
                   "heldout_track_median_mm": 1e3 * m["heldout_track_median_m"], "params": m["params"]}
                  for m in content["models"]],
        "pooled_all": {"drag_coefficient": both.params["quadratic_drag"]["drag_coefficient"],
                       "lift_coefficient": both.params["magnus"]["lift_coefficient"],
                       "rms": [row(problem.fit((), None)), row(drag_only), row(both)]},
        "per_ball": {"drag_coefficient": robust(cd), "lift_coefficient": robust(cl),
                     "lift_coefficient_std_at_median_S": float(np.median(cl) * np.median(spin_ratio))},
        "spin_check": {"fraction_direction_agrees": float(agree.mean()),
                       "cosine_percentiles": np.percentile(consistency["cosine"].numpy(), [10, 25, 50, 75, 90]).tolist(),
                       "rms_mm_with_fitted_spin": 1e3 * consistency["rms_m"],
                       "lift_per_measured_spin_agreeing": robust(consistency["ratio"].numpy()[agree])},
        "pooled_agreeing": {"flights": int(agree.sum()), "verdict": sub_content["verdict"],
                            "indistinguishable": sub_content["indistinguishable"],
                            "steps": [{"effects": m["effects"], "rms_mm": 1e3 * m["rms_m"],
                                       "heldout_rms_mm": 1e3 * m["heldout_rms_m"],
                                       "heldout_track_median_mm": 1e3 * m["heldout_track_median_m"],
                                       "params": m["params"]}
                                      for m in sub_content["models"]],
                            "drag_coefficient": sub_both.params["quadratic_drag"]["drag_coefficient"],
                            "lift_coefficient": sub_both.params["magnus"]["lift_coefficient"],
                            "rms": [row(sub_problem.fit((), None)), row(sub_drag), row(sub_both)]},
        "backcast": backcast,
        "seconds": time.perf_counter() - clock,
    }
    numbers = np.array([t.meta["trajectory"] for t in tracks])
    figures(summary, cd, cl, spin_ratio, agree, out_dir, numbers, consistency["cosine"].numpy())
    summary["figures"] = ["pre_bounce/residuals.png", "agreeing/residuals.png", "rms_steps.png", "lift.png",
                          "spin_check.png"]
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    say(json.dumps({k: summary[k] for k in ("verdict", "steps", "per_ball", "spin_check")}, indent=1)[:4000])
    return summary


def figures(summary: dict, cd, cl, spin_ratio, agree, out_dir: Path, numbers, cosine) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    runs = [(summary["steps"], f"all pre-bounce flights (n={summary['data']['flights']})"),
            (summary["pooled_agreeing"]["steps"], f"spin agrees with flight (n={summary['pooled_agreeing']['flights']})")]
    for ax, (steps, title) in zip(axes, runs):
        labels = ["baseline" if not s["effects"] else "+ " + s["effects"][-1] for s in steps]
        rms = [s["rms_mm"] for s in steps]
        held = [s["heldout_rms_mm"] for s in steps]
        x = np.arange(len(labels))
        ax.bar(x - 0.2, rms, 0.4, label="fit RMS (all samples)")
        ax.bar(x + 0.2, held, 0.4, label="held-out RMS (first and last 25% predicted, mean)"
               if summary["backcast"] else "held-out RMS (last 25% predicted)")
        ax.axhline(summary["data"]["noise_rms_mm"], color="k", ls="--", lw=1, label="noise")
        for xi, (r, h) in enumerate(zip(rms, held)):
            ax.text(xi - 0.2, r, f"{r:.1f}", ha="center", va="bottom", fontsize=8)
            ax.text(xi + 0.2, h, f"{h:.1f}", ha="center", va="bottom", fontsize=8)
        ax.set_xticks(x, labels, fontsize=8)
        ax.set_ylabel("position error (mm)")
        ax.set_title(f"{title}: effects in the order added", fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_dir / "rms_steps.png", dpi=90)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    axes[0].hist(cd, bins=np.linspace(0, 1.2, 41), color="C0")
    axes[0].axvline(np.median(cd), color="k", lw=1)
    axes[0].set_xlabel("drag coefficient C_d (per ball)")
    axes[0].set_ylabel("balls")
    std_cl = cl * spin_ratio
    axes[1].scatter(spin_ratio[agree], std_cl[agree], s=8, label="measured spin agrees in direction")
    axes[1].scatter(spin_ratio[~agree], std_cl[~agree], s=8, marker="x", label="disagrees")
    axes[1].set_xlabel("spin ratio S = r|ω⊥|/|v|")
    axes[1].set_ylabel("C_L,std = C_L · S (per ball)")
    axes[1].set_ylim(-1, 1.5)
    axes[1].axhline(0, color="k", lw=0.5)
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_dir / "lift.png", dpi=90)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 3))
    ax.scatter(numbers, cosine, s=8)
    ax.axhline(0.5, color="k", lw=0.5, ls="--")
    ax.set_xlabel("SpinDOE trajectory number")
    ax.set_ylabel("cos(measured ω⊥, flight's ω⊥)")
    ax.set_title("does the measured spin point where the flight's curvature says? (⊥: across the velocity)", fontsize=9)
    fig.tight_layout()
    fig.savefig(out_dir / "spin_check.png", dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    parser.add_argument("--limit", type=int, default=None, help="first N trajectories only (a smoke run)")
    parser.add_argument("--backcast", action="store_true",
                        help="hold out each flight's first quarter as well, predicted backward")
    args = parser.parse_args()
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    main(args.out, args.limit, args.backcast)
