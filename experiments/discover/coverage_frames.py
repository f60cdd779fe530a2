"""Per frame, how far the segmentation's soft coverage and mask lie from the engine's exact mask.

    python experiments/discover/coverage_frames.py SET NAME [well_posed_grey=G]   # ~20 s

For one concealed recording (``SET``: a folder of recordings beside this file, e.g.
``recordings_fresh6``), segmented as discover does on video (one albedo pass, the settings'
defaults, ``well_posed_grey`` if given), prints per frame the soft coverage's area over the exact
mask's and its centroid minus the exact one's (``dx``, ``dy``, px), the same for the hard mask,
and the exact centroid. The exact masks are the frame's instant, so a blurred frame's coverage
differs from them by the blur's own asymmetry too (a few hundredths of a pixel at these speeds).
Written for HISTORY.md *Sixty-first session* (a clip's first frames over a dark cabinet).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from true_masks import recording_parts

from torchfit.video import SegmentationSettings, load_observation, raw_moments

HERE = Path(__file__).resolve().parent


def centroids(moments: np.ndarray) -> np.ndarray:
    """(T, 2) centroids (x, y), px, of (T, 6) raw moments (each frame non-empty)."""
    return moments[:, 1:3] / moments[:, :1]


def frame_errors(folder: Path, well_posed_grey: float | None = None) -> dict:
    """The recording ``folder``'s per-frame errors: ``area`` (T,) coverage area / exact area,
    ``coverage`` and ``mask`` (T, 2) centroid offsets (px) of the soft coverage and the hard mask
    from the exact mask, ``exact`` (T, 2) the exact centroid (px)."""
    _, _, camera = recording_parts(folder)
    settings = SegmentationSettings(albedo_passes=1, **({} if well_posed_grey is None
                                                        else {"well_posed_grey": well_posed_grey}))
    observation = load_observation(str(folder / "video.mp4"), camera=camera, settings=settings)
    exact = raw_moments(np.load(folder / "masks.npz")["masks"].astype(bool))
    coverage, mask = np.asarray(observation.coverage_moments), raw_moments(observation.masks)
    return {"area": coverage[:, 0] / exact[:, 0], "coverage": centroids(coverage) - centroids(exact),
            "mask": centroids(mask) - centroids(exact), "exact": centroids(exact)}


def main(argv: list[str]) -> None:
    grey = [a for a in argv if a.startswith("well_posed_grey=")]
    names = [a for a in argv if a not in grey]
    if len(names) != 2:
        raise SystemExit("usage: coverage_frames.py SET NAME [well_posed_grey=G]")
    folder = HERE / names[0] / names[1]
    if not (folder / "masks.npz").is_file():
        raise SystemExit(f"{folder}: no recording (make_concealed.py makes the sets)")
    found = frame_errors(folder, float(grey[0].split("=", 1)[1]) if grey else None)
    print("frame  area   coverage dx, dy   mask dx, dy   exact centroid")
    for t, (area, c, m, e) in enumerate(zip(found["area"], found["coverage"], found["mask"], found["exact"])):
        print(f"{t:5d}  {area:.3f}  {c[0]:+6.2f} {c[1]:+6.2f}   {m[0]:+6.2f} {m[1]:+6.2f}   ({e[0]:.0f}, {e[1]:.0f})")


if __name__ == "__main__":
    main(sys.argv[1:])
