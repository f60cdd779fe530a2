"""Does the segmentation's coverage read a shaded ball's outline right? (issue 6, HISTORY.md,
*Nineteenth session*)

A synthetic disc on a smooth coloured background, flat or shaded like a Lambertian sphere lit
from the camera (``LIMB`` of its centre's brightness at the limb), blurred by a travel of 0-15 px
(a frame's travel of at least 10 px), without noise or codec, segmented with the albedo pass.
Printed: the soft coverage's area over the exact coverage's, and the excess of its variance along
and across the motion (px^2), within the band of 4 steps and the band swept along the motion,
and for the shaded disc with other shading radii (``SegmentationSettings.shading_radius``) and the
local-linear shading (``SegmentationSettings.shading_fit="linear"``).

    python experiments/discover/shading_limb.py     # ~1 min
"""

from __future__ import annotations

import numpy as np
import torch

from torchfit.losses import central_moments
from torchfit.video import SegmentationSettings, _segment, raw_moments

LIMB = 0.3


def frames_of(blur_px: float, shaded: bool, speed: float = 10.0, radius: float = 12.0, samples: int = 4,
              steps: int = 21, frames: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """(T, H, W, 3) uint8 frames of the disc moving ``speed`` px a frame along x, blurred by
    ``blur_px`` of travel (``steps`` positions averaged, ``samples`` x ``samples`` sub-samples a
    pixel), and (T, H, W) its exact coverage."""
    height, width = 100, 260
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    scene = np.stack([90 + 0.2 * xx, 100 + 0.3 * yy, 120 - 0.1 * xx], -1)
    fine_scene = np.repeat(np.repeat(scene, samples, 0), samples, 1)
    colour = np.array([60.0, 140.0, 200.0])
    ys, xs = np.mgrid[0:height * samples, 0:width * samples] / samples + 0.5 / samples - 0.5
    images, covers = [], []
    for t in range(frames):
        cover, light = np.zeros_like(xs), np.zeros(xs.shape + (3,))
        for k in range(steps):
            centre = 20 + speed * t + (k / (steps - 1) - 0.5) * blur_px
            r2 = ((xs - centre) ** 2 + (ys - 50) ** 2) / radius**2
            inside = r2 <= 1
            shade = LIMB + (1 - LIMB) * np.sqrt(np.clip(1 - r2, 0, 1)) if shaded else np.ones_like(r2)
            cover += inside
            light += (inside * shade)[..., None] * colour
        cover, light = cover / steps, light / steps + (1 - cover / steps)[..., None] * fine_scene
        images.append(np.clip(np.round(light.reshape(height, samples, width, samples, 3).mean((1, 3))), 0, 255))
        covers.append(cover.reshape(height, samples, width, samples).mean((1, 3)))
    return np.array(images, dtype=np.uint8), np.array(covers)


def excess(blur_px: float, shaded: bool, **settings) -> tuple[float, float, float]:
    """Area ratio and the variance's excess along and across the motion (px^2), mean over the
    inner frames, of the coverage segmented with ``settings`` (and the albedo pass)."""
    frames, covers = frames_of(blur_px, shaded, speed=max(blur_px, 10.0))
    inner = slice(3, -3)
    exact = central_moments(torch.as_tensor(raw_moments(covers[inner])))
    out = _segment(frames, SegmentationSettings(albedo_passes=1, **settings))
    seen = central_moments(torch.as_tensor(out["coverage_moments"][inner]))
    extra = (seen[2] - exact[2]).mean(0).numpy()
    return float((seen[0] / exact[0]).mean()), float(extra[0, 0]), float(extra[1, 1])


def main() -> None:
    print("| disc | blur (px) | band | shading radius and fit | area | along (px²) | across (px²) |\n|---|---|---|---|---|---|---|")
    rows = [(shaded, blur, band, 1.5) for shaded in (False, True) for blur in (0.0, 5.0, 10.0, 15.0)
            for band in ("steps", "motion")]
    rows += [(True, blur, "motion", r) for r in (0.0, 0.75, 3.0) for blur in (0.0, 10.0)]
    rows = [row + ("constant",) for row in rows]
    rows += [(shaded, blur, "motion", r, "linear") for shaded in (False, True) for r in (1.5, 3.0)
             for blur in (0.0, 5.0, 10.0)]
    for shaded, blur, band, r, fit in rows:
        area, along, across = excess(blur, shaded, coverage_band=band, coverage_clip=False, shading_radius=r,
                                     shading_fit=fit)
        print(f"| {'shaded' if shaded else 'flat'} | {blur:g} | {band} | {r:g} {fit} | {area:.4f} | {along:+.2f} "
              f"| {across:+.2f} |", flush=True)


if __name__ == "__main__":
    main()
