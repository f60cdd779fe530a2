"""The segmentation's mean edge bias on every recording with true masks: how far (pixels, along the
normal) the outline of torchfit.video's masks lies outside the true one, (area - true area) /
true perimeter, averaged over the used frames. It is what discover's edge-bias nuisance estimates
(`models[].edge_px` in discover.json) and what its prior (`EDGE_PRIOR_PX`) is set from.

    python experiments/discover/edge_bias.py      # ~1 min; writes results/edge_bias.json
"""

import json
from pathlib import Path

import numpy as np

from torchfit.video import load_observation

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = [ROOT / "torchfit" / "recordings", ROOT / "experiments" / "discover" / "recordings"]


def outline(masks: np.ndarray) -> np.ndarray:
    """(T, H, W) bool: the pixels of (T, H, W) bool masks with a 4-neighbour outside the mask."""
    inner = masks.copy()
    inner[:, 1:-1, 1:-1] &= masks[:, :-2, 1:-1] & masks[:, 2:, 1:-1] & masks[:, 1:-1, :-2] & masks[:, 1:-1, 2:]
    return masks & ~inner


def edge_bias(folder: Path) -> float:
    observation = load_observation(folder / "video.mp4", camera=folder / "camera.json")
    with np.load(folder / "masks.npz") as data:
        truth = data["masks"].astype(bool)
    perimeter = outline(truth).sum((1, 2))
    bias = (observation.masks.sum((1, 2)) - truth.sum((1, 2))) / np.maximum(perimeter, 1)
    return float(bias[observation.used].mean())


def main() -> dict:
    rows = {}
    for base in FOLDERS:
        for folder in sorted(p for p in base.glob("*") if (p / "masks.npz").exists() and (p / "video.mp4").exists()):
            rows[folder.name] = edge_bias(folder)
            print(f"{folder.name:22s} {rows[folder.name]:+.3f} px", flush=True)
    return rows


if __name__ == "__main__":
    out = Path(__file__).resolve().parent / "results" / "edge_bias.json"
    out.write_text(json.dumps(main(), indent=1))
