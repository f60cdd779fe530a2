"""Where the segmentation's IoU is lost, and how it carries to recordings it was not tuned on.

    MUJOCO_GL=osmesa python experiments/segmentation_limits.py [--work DIR]   # ~4 min, needs .[recordings]

Three tables, printed and written to ``experiments/segmentation_limits.json``:

1. ``blur``: MuJoCo's own coverage of each shipped recording (the mean of its sub-frame
   segmentation renders) thresholded at 0.5, against the true mask at the frame time. This is
   what a perfect coverage estimate would score: the limit the motion blur sets.
2. ``held_out``: four recordings drawn with other seeds and spins (not used to choose any
   setting), segmented with the per-pixel shading fit only (``shading_radius=0``) and with the
   local shading (the default).
3. ``small``: variants of ``tshape_small`` (the size and shutter of the earlier shipped one),
   with the same two settings.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from torchfit.video import SegmentationSettings

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "recordings"))
sys.path.insert(0, str(HERE))
import make_recordings as mr  # noqa: E402  (MuJoCo: the `recordings` extra)
from segmentation_iou import frame_ious  # noqa: E402

SETTINGS = {"per_pixel": SegmentationSettings(shading_radius=0.0), "local": SegmentationSettings()}


def held_out_specs() -> list:
    spec = mr.RecordingSpec
    return [
        spec(name="h_tshape", shape="tshape", spin_rate=12.0, spin_axis="major", seed=21, tilt_deg=5.0),
        spec(name="h_tshape_int", shape="tshape", spin_rate=18.0, spin_axis="intermediate", seed=22,
             roll_deg=8.0),
        spec(name="h_box", shape="box", spin_rate=10.0, spin_axis="random", seed=23),
        spec(name="h_cyl", shape="cylinder", spin_rate=8.0, spin_axis="random", seed=24,
             depth_range=(1.5, 1.8)),
    ]


def small_specs() -> list:
    small = next(s for s in mr.shipped_specs() if s.name == "tshape_small")
    return [
        small.replace(name="small_160_1of60", width=160, height=120, exposure=0.5),
        small.replace(name="small_320_1of60", exposure=0.5),
        small.replace(name="small_160_1of300", width=160, height=120),
    ]


def blur_limit(spec) -> dict:
    """IoU of MuJoCo's sub-frame coverage >= 0.5 against the frame-time mask, per frame."""
    mesh = mr.make_mesh(spec.shape, spec.ball_radius)
    scene = mr.Scene(spec, mesh)
    mj, model, data = scene.mj, scene.model, scene.data
    ic, _ = mr.resolve_ic(spec, scene, mesh)
    frame_times, sub_times = mr.sample_times(spec)
    times = np.unique(np.concatenate([frame_times, sub_times.ravel()]))
    qpos = scene.simulate(ic, times)
    index = {float(t): i for i, t in enumerate(times)}
    width, height, _ = mr.render_geometry(spec)
    renderer = mj.Renderer(model, height, width)
    renderer.enable_segmentation_rendering()

    def mask(t: float) -> np.ndarray:
        data.qpos[:] = qpos[index[float(t)]]
        data.qvel[:] = 0.0
        mj.mj_forward(model, data)
        renderer.update_scene(data, camera="cam")
        return mr.object_mask(renderer.render(), scene)

    try:
        ious = []
        for i, t in enumerate(frame_times):
            covered = np.mean([mask(s) for s in sub_times[i]], axis=0) >= 0.5
            truth = mask(t)
            ious.append((covered & truth).sum() / max((covered | truth).sum(), 1))
    finally:
        renderer.close()
    return {"median": float(np.median(ious)), "worst": float(np.min(ious))}


def segmentation_iou(folder: Path) -> dict:
    """{setting: {median, worst}} of torchfit.video's masks against the true masks."""
    out = {}
    for name, settings in SETTINGS.items():
        iou, _ = frame_ious(folder, settings)
        out[name] = {"median": float(np.median(iou)), "worst": float(iou.min())}
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=None, help="folder for the recordings (default: a temporary one)")
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="segmentation_limits_"))
    result: dict = {"blur": {}, "held_out": {}, "small": {}}
    for spec in mr.shipped_specs():
        result["blur"][spec.name] = row = blur_limit(spec)
        print(f"blur limit  {spec.name:22s} median {row['median']:.3f}  worst {row['worst']:.3f}", flush=True)
    for table, specs in (("held_out", held_out_specs()), ("small", small_specs())):
        for spec in specs:
            mr.make_recording(spec, work, verbose=False)
            result[table][spec.name] = row = segmentation_iou(work / spec.name)
            print(f"{table:11s} {spec.name:22s} " + "  ".join(
                f"{k}: median {v['median']:.3f} worst {v['worst']:.3f}" for k, v in row.items()), flush=True)
    (HERE / "segmentation_limits.json").write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
