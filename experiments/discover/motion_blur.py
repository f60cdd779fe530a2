"""Does motion blur explain the segmentation's error? Renders at the true poses, with and without the exposure.

    python experiments/discover/motion_blur.py [names...]     # ~30 s per recording

The recordings average ``blur_subframes`` renders over ``exposure_frac`` of the frame interval
(truth.json ``render``); the true mask (``masks.npz``) is the mid-exposure one. A segmentation that
thresholds the blurred coverage at 0.5 would see the object where it covers the pixel for more
than half the exposure, which is not the mid-exposure silhouette (a blurred disc's 0.5 contour is
narrower across the motion). If that were the segmentation's error, rendering the same average
(sub-frame poses from a cubic spline of the true positions and a rotation spline of the true
orientations) and thresholding it should match the segmented masks better than the mid-exposure
render does. For each recording, the five residual channels (mean / RMS over the used frames) of

* ``true-mid``: true masks against the mid-exposure render (the renderer's own error),
* ``seg-mid``: segmented masks against the mid-exposure render,
* ``seg-blur``: segmented masks against the exposure-averaged render thresholded at 0.5,
* ``true-blur``: true masks against the exposure-averaged one (what the blur alone changes).

Writes results/motion_blur.json. Recordings: experiments/discover/recordings (make_concealed.py).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline
from true_masks import recording_parts, subframe_times

from torchfit.discover_video import _moments
from torchfit.losses import mask_moments
from torchfit.render import RenderMesh, crop_windows, render_silhouettes
from torchfit.residuals import CHANNELS, channel_values
from torchfit.video import _boxes, load_observation

HERE = Path(__file__).resolve().parent
CROP, SIGMA = 128, 0.25  # finer than discover's (96, 0.25): the renderer's own error stays small
RAMP = 0.1  # the 0.5 threshold as a ramp this wide in coverage (a sub-pixel edge position)


def measure(folder: Path) -> dict:
    """Per comparison, per channel ``{"mean", "rms"}`` over the used frames."""
    truth, shape, camera = recording_parts(folder)
    per_frame = truth["per_frame"]
    position, rotation = np.array(per_frame["position"]), np.array(per_frame["R"])
    observation = load_observation(str(folder / "video.mp4"), camera=camera)
    segmented = observation.masks.astype(bool)
    true = np.load(folder / "masks.npz")["masks"].astype(bool)
    times, sub_times = subframe_times(truth)  # as the recordings place them
    sub_times = np.clip(sub_times, times[0], times[-1])  # (T, K)
    sub_position = CubicSpline(times, position)(sub_times)  # (T, K, 3)
    sub_rotation = RotationSpline(times, Rotation.from_matrix(rotation))(sub_times.ravel()).as_matrix()
    sub_rotation = sub_rotation.reshape(*sub_times.shape, 3, 3)
    mesh = RenderMesh.from_shape(shape, torch.float64)
    windows = crop_windows(torch.as_tensor(_boxes(segmented | true), dtype=torch.float64), (CROP, CROP), margin=0.4)

    def render(rot: np.ndarray, trans: np.ndarray) -> torch.Tensor:
        return render_silhouettes(mesh, camera, torch.as_tensor(rot)[None], torch.as_tensor(trans)[None],
                                  windows[None], size=(CROP, CROP), sigma=SIGMA)[0]

    with torch.no_grad():
        mid = render(rotation, position)
        average = torch.stack([render(sub_rotation[:, k], sub_position[:, k]) for k in range(sub_times.shape[1])]).mean(0)
        blurred = ((average - 0.5) / RAMP + 0.5).clamp(0.0, 1.0)
    used = observation.used
    observed = {kind: mask_moments(torch.as_tensor(masks, dtype=torch.float64))
                for kind, masks in (("true", true), ("seg", segmented))}
    fitted = {"mid": _moments(mid, windows), "blur": _moments(blurred, windows)}
    out = {}
    for label in ("true-mid", "seg-mid", "seg-blur", "true-blur"):
        kind, render_kind = label.split("-")
        channels = channel_values(observed[kind], fitted[render_kind])
        out[label] = {c: {"mean": float(channels[c][used].mean()), "rms": float(channels[c][used].pow(2).mean().sqrt())}
                      for c in CHANNELS}
    return out


def main(names: list[str]) -> None:
    out = HERE / "results" / "motion_blur.json"
    results = json.loads(out.read_text()) if out.exists() else {}
    print("recording        comparison " + " ".join(f"{c:>20s}" for c in CHANNELS) + "   (mean / RMS)")
    for name in names or ["drag_light_ball", "drag_foam_ball", "control_ball", "magnus_tshape", "magnus_cylinder"]:
        results[name] = measure(HERE / "recordings" / name)
        for label, row in results[name].items():
            print(f"{name:16s} {label:10s} " + " ".join(f"{row[c]['mean']:+9.4f} / {row[c]['rms']:.4f}"
                                                        for c in CHANNELS), flush=True)
    out.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main(sys.argv[1:])
