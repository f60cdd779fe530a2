"""Where the segmentation errs on a concealed recording, frame by frame, and whether it knows.

    python experiments/discover/segmentation_error.py [names...]   # ~1 min per recording

For each frame: the segmented mask against MuJoCo's true mask (centroid error in px, edge bias =
area difference / true perimeter in px), and the median object-background contrast |F - B| (grey
levels, from the segmentation's own local shading fit) along the true outline. Prints them and
the correlation of |edge bias| with 1 / contrast: if low contrast explained the errors, a
per-frame noise floor from the contrast would weigh the bad frames down. Writes
results/segmentation_error.json. Recordings: experiments/discover/recordings (make_concealed.py).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from edge_bias import outline

import torchfit.video as video

HERE = Path(__file__).resolve().parent


def segment_watching(folder: Path, hook: str, keep,
                     settings: video.SegmentationSettings | None = None) -> tuple[np.ndarray, list, np.ndarray]:
    """Segment a concealed recording's video as torchfit does, watching one step of it.

    Args:
        folder: the recording (video.mp4, masks.npz).
        hook: a function of :mod:`torchfit.video` that ``_segment`` calls once per frame
            (``_local_contrast``, ``_local_shading_coverage``).
        keep: what to keep of each call's result.
        settings: the segmentation's settings (default: the defaults).

    Returns:
        (T, H, W) segmented masks, the T kept values (frame order), (T, H, W) true masks.
    """
    kept = []
    original = getattr(video, hook)

    def recording(*args):
        result = original(*args)
        kept.append(keep(result))
        return result

    frames, _ = video._read_video(folder / "video.mp4", 0, None)
    setattr(video, hook, recording)
    try:
        segmented = video._segment(frames, settings or video.SegmentationSettings())["masks"]
    finally:
        setattr(video, hook, original)
    true = np.load(folder / "masks.npz")["masks"].astype(bool)
    if len(kept) != len(true):
        raise RuntimeError(f"{folder.name}: {len(kept)} segmented frames, {len(true)} true masks")
    return segmented, kept, true


def mask_centroids(masks: np.ndarray) -> np.ndarray:
    """(T, 2) centroids (x, y), pixels, of (T, H, W) bool masks (each non-empty)."""
    return np.array([[xs.mean(), ys.mean()] for ys, xs in (np.nonzero(m) for m in masks)])


def frame_errors(segmented: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T,) each: the segmented mask's centroid minus the true one's, x and y (px), and its edge
    bias (area difference over the true outline's 4-connected length, px), from (T, H, W) bool
    segmented and true masks."""
    delta = mask_centroids(segmented) - mask_centroids(true)
    edge = (segmented.sum((1, 2)) - true.sum((1, 2))) / outline(true).sum((1, 2))
    return delta[:, 0], delta[:, 1], edge


def measure(folder: Path) -> dict:
    # per frame |F - B| (H, W) along the outline, from the local-shading coverage's contrast fit
    segmented, contrasts, true = segment_watching(
        folder, "_local_contrast", lambda result: np.linalg.norm(result[0], axis=-1))
    outlines = outline(true)
    dx, dy, edge_px = frame_errors(segmented, true)
    rows = [{"frame": t, "dx": float(dx[t]), "dy": float(dy[t]), "edge_px": float(edge_px[t]),
             "contrast": float(np.median(contrasts[t][outlines[t]]))} for t in range(len(true))]
    error = np.abs([r["edge_px"] for r in rows])
    inverse = 1.0 / np.array([r["contrast"] for r in rows])
    return {"frames": rows, "corr_abs_edge_inverse_contrast": float(np.corrcoef(error, inverse)[0, 1])}


def main(names: list[str]) -> None:
    out = HERE / "results" / "segmentation_error.json"
    results = json.loads(out.read_text()) if out.exists() else {}
    for name in names or ["drag_foam_ball", "magnus_tshape"]:
        result = measure(HERE / "recordings" / name)
        results[name] = result
        rows = result["frames"]
        print(f"== {name}: corr(|edge bias|, 1/contrast) = {result['corr_abs_edge_inverse_contrast']:.2f}")
        for key in ("edge_px", "dx", "dy", "contrast"):
            print(f"  {key:8s}", " ".join(f"{r[key]:.2f}" for r in rows))
    out.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main(sys.argv[1:])
