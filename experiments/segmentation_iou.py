"""Segmentation IoU of torchfit.video against the true masks of every shipped recording.

    python experiments/segmentation_iou.py
"""

import json
from pathlib import Path

import numpy as np

from torchfit.video import SegmentationSettings, load_observation

DATA = Path(__file__).resolve().parents[1] / "torchfit" / "recordings"


def frame_ious(folder: Path, settings: SegmentationSettings | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(T,) IoU of the segmented masks of ``folder/video.mp4`` against ``folder/masks.npz``,
    and the (T,) bool used flags of the observation."""
    obs = load_observation(folder / "video.mp4", camera=folder / "camera.json", settings=settings)
    with np.load(folder / "masks.npz") as data:
        truth = data[data.files[0]].astype(bool)
    iou = (obs.masks & truth).sum((1, 2)) / np.maximum((obs.masks | truth).sum((1, 2)), 1)
    return iou, obs.used


def main() -> dict:
    rows = {}
    for folder in sorted(p for p in DATA.iterdir() if (p / "video.mp4").exists()):
        iou, used = frame_ious(folder)
        rows[folder.name] = {"median": float(np.median(iou[used])), "worst": float(iou[used].min()),
                             "frames": int(len(iou)), "used": int(used.sum())}
        print(f"{folder.name:22s} median {rows[folder.name]['median']:.3f}  worst {rows[folder.name]['worst']:.3f}"
              f"  ({rows[folder.name]['used']}/{rows[folder.name]['frames']} frames used)")
    return rows


if __name__ == "__main__":
    json.dump(main(), open(Path(__file__).with_suffix(".json"), "w"), indent=1)
