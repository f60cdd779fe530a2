"""How far torchfit's soft silhouettes at the true poses sit from the true masks, per render setting.

    python experiments/discover/render_bias.py [names...]     # ~1 min for the four default recordings

For each shipped MuJoCo recording, render the mesh at the true pose of every frame
(``truth.json``) with the sigmoid-edge renderer at several (crop, sigma) settings, and compare the
five residual channels of :mod:`torchfit.residuals` with those of the true masks (``masks.npz``,
MuJoCo's own segmentation, no video): dynamics and segmentation are out of the loop, what is left
is the renderer (``torchfit.discover_video.render_residuals``); ``exact`` is the polygon's moments
(:func:`torchfit.render.silhouette_moments`), which discover's refits use since 2026-11-26. A sigmoid edge overshoots at convex
corners (the distance is the largest edge-line distance), so the soft silhouette is larger than the
polygon by about (sigma * stride)^2 per corner; the mean of ``scale`` (log size) shows that bias,
the spread of ``shape`` the part that follows the pose. Writes results/render_bias.json.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

from torchfit.discover_video import render_residuals
from torchfit.paper._recording import load_recording

SETTINGS = ((64, 0.5), (64, 0.25), (96, 0.25), (128, 0.25), (256, 0.25), (None, None))  # None: exact moments
OUT = Path(__file__).resolve().parent / "results" / "render_bias.json"


def render_bias(name: str) -> dict:
    """Per ``"crop/sigma"``: mean stride, and each channel's mean and standard deviation over the frames."""
    rec = load_recording(name)
    truth = json.loads((rec.folder / "truth.json").read_text())["per_frame"]
    masks = np.load(rec.folder / "masks.npz")["masks"].astype(bool)
    rot, trans = torch.tensor(truth["R"]), torch.tensor(truth["position"])
    out = {}
    for crop, sigma in SETTINGS:
        channels = render_residuals(rec.shape, rec.camera, rot, trans, masks, crop, sigma)
        stride = channels.pop("stride")
        out["exact" if crop is None else f"{crop}/{sigma}"] = {"stride_px": float(stride.mean()),
                                  **{k: {"mean": float(v.mean()), "std": float(v.std())} for k, v in channels.items()}}
    return out


if __name__ == "__main__":
    names = sys.argv[1:] or ["tshape", "tshape_intermediate", "box_fast", "cylinder"]
    results = {}
    print("recording           crop/sigma stride  scale mean %  shape mean %  shape std %  centroid std px")
    for name in names:
        results[name] = render_bias(name)
        for setting, row in results[name].items():
            centroid = np.hypot(row["centroid_x"]["std"], row["centroid_y"]["std"])
            print(f"{name:20s} {setting:9s} {row['stride_px']:5.2f}  {100 * row['scale']['mean']:+11.3f}  "
                  f"{100 * row['shape']['mean']:+12.3f}  {100 * row['shape']['std']:11.3f}  {centroid:15.3f}",
                  flush=True)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(results, indent=1))
