"""Success rate of the no-guess fit over random MuJoCo throws (issue: multi-start search).

Makes N recordings of random T-handle throws with MuJoCo (random orientation, spin 2-20 rad/s
about the major, intermediate or a random axis), fits each with `experiment=fit` and the default
search, scores it against the truth and writes a table and JSON.

    MUJOCO_GL=osmesa python experiments/fit/benchmark.py --n 20 --out experiments/fit/results
    python experiments/fit/benchmark.py --quick          # CI: the shipped tshape_small, quick search

Success (per recording): rotation error ≤ 5° modulo symmetry at frame 0 (or the truth among the
reported alternatives within 1.25× of the best loss), position error ≤ 2 % of depth, gravity
direction ≤ 2°, and mean IoU ≥ 0.9 against the true masks.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def make_specs(n: int, seed: int):
    sys.path.insert(0, str(ROOT / "experiments" / "recordings"))
    import make_recordings as mr  # noqa: E402 - optional MuJoCo extra

    rng = np.random.default_rng(seed)
    axes = ["major", "intermediate", "random"]
    specs = []
    for i in range(n):
        specs.append(mr.RecordingSpec(
            name=f"throw{i:02d}", shape="tshape", spin_rate=float(rng.uniform(2.0, 20.0)),
            spin_axis=axes[i % 3], spin_wobble=float(rng.uniform(0.05, 0.4)),
            tilt_deg=float(rng.uniform(-15, 15)), roll_deg=float(rng.uniform(-15, 15)),
            seed=1000 + seed * 100 + i, scene_seed=i % 4))
    return mr, specs


def true_iou(result: dict, folder: Path) -> float:
    import cv2  # noqa: F401 - imported for its side effects on some builds
    import torch

    from torchfit.camera import Camera
    from torchfit.render import RenderMesh, full_window, render_silhouettes
    from torchfit.shape import load_shape

    camera = Camera.from_file(folder / "camera.json")
    shape = load_shape(folder / "mesh.obj", density=600.0)
    rot = torch.tensor(result["per_frame"]["R"], dtype=torch.float32)
    trans = torch.tensor(result["per_frame"]["position"], dtype=torch.float32)
    with torch.no_grad():
        fitted = render_silhouettes(RenderMesh.from_shape(shape), camera, rot[None], trans[None],
                                    full_window(camera, 1, len(rot)), size=(camera.height, camera.width),
                                    sigma=None)[0].numpy() > 0.5
    with np.load(folder / "masks.npz") as data:
        truth = data[data.files[0]].astype(bool)
    inter = (fitted & truth).sum((1, 2))
    union = np.maximum((fitted | truth).sum((1, 2)), 1)
    return float(np.mean(inter / union))


def fit_one(folder: Path, out: Path, overrides: list[str]) -> dict:
    from hydra import compose, initialize_config_module

    from torchfit.run import run

    with initialize_config_module(config_module="torchfit.configs", version_base="1.3"):
        cfg = compose(config_name="config", overrides=[
            "experiment=fit", f"data.video={folder / 'video.mp4'}", f"object.mesh={folder / 'mesh.obj'}",
            f"camera.file={folder / 'camera.json'}", f"data.truth={folder / 'truth.json'}", "quiet=true",
            "outputs.overlay_video=false", *overrides])
    started = time.perf_counter()
    result = run(cfg, out)
    truth = result["truth"]
    row = {
        "recording": folder.name,
        "rotation_error_deg": truth["rotation_error_deg"],
        "position_error_pct_depth": truth["position_error_pct_depth"],
        "gravity_error_deg": truth["gravity_error_deg"],
        "angular_velocity_error": truth.get("angular_velocity_error"),
        "spin": truth.get("angular_velocity_true_norm"),
        "truth_among_alternatives": truth["truth_among_alternatives"],
        "mean_iou_true_masks": true_iou(result, folder),
        "seconds": time.perf_counter() - started,
    }
    row["success"] = bool(truth["success"] and row["mean_iou_true_masks"] >= 0.9)
    return row


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=20, help="number of random recordings")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=ROOT / "experiments" / "fit" / "results")
    parser.add_argument("--work", type=Path, default=Path("/tmp/torchfit_fit_benchmark"),
                        help="where recordings and run folders go (not committed)")
    parser.add_argument("--quick", action="store_true", help="shipped tshape_small, quick search (no MuJoCo)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    if args.quick:
        folder = ROOT / "torchfit" / "recordings" / "tshape_small"
        rows.append(fit_one(folder, args.work / "quick", ["search=quick"]))
    else:
        mr, specs = make_specs(args.n, args.seed)
        for spec in specs:
            folder = args.work / "recordings" / spec.name
            if not (folder / "truth.json").exists():
                mr.make_recording(spec, args.work / "recordings", verbose=False)
            row = fit_one(folder, args.work / "runs" / spec.name, [])
            row["spin_axis"] = spec.spin_axis
            rows.append(row)
            print(json.dumps(row), flush=True)
    summary = {
        "n": len(rows),
        "success_rate": float(np.mean([r["success"] for r in rows])),
        "median_seconds": float(np.median([r["seconds"] for r in rows])),
        "rows": rows,
    }
    name = "quick.json" if args.quick else "benchmark.json"
    (args.out / name).write_text(json.dumps(summary, indent=1))
    print(table(summary))
    return summary


def table(summary: dict) -> str:
    lines = ["| recording | spin axis | spin rad/s | rotation ° | position % depth | gravity ° | spin err rad/s | "
             "IoU (true masks) | s | success |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in summary["rows"]:
        lines.append(
            f"| {r['recording']} | {r.get('spin_axis', '-')} | {r['spin'] or float('nan'):.1f} | "
            f"{r['rotation_error_deg']:.2f} | {r['position_error_pct_depth']:.2f} | {r['gravity_error_deg']:.2f} | "
            f"{(r['angular_velocity_error'] if r['angular_velocity_error'] is not None else math.nan):.2f} | "
            f"{r['mean_iou_true_masks']:.3f} | {r['seconds']:.0f} | {'yes' if r['success'] else 'no'} |")
    lines.append(f"\nsuccess {100 * summary['success_rate']:.0f}% of {summary['n']}, "
                 f"median {summary['median_seconds']:.0f} s per fit")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
