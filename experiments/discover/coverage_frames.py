"""Per frame, how far the segmentation's soft coverage and mask lie from the engine's exact mask.

    python experiments/discover/coverage_frames.py SET NAME [SETTING=VALUE ...]    # ~20 s
    python experiments/discover/coverage_frames.py SET --dark [SETTING=VALUE ...]  # ~20 s a recording

For one concealed recording (``SET``: a folder of recordings beside this file, e.g.
``recordings_fresh6``), segmented as discover does on video (one albedo pass, the settings'
defaults but for any ``SETTING=VALUE`` given: ``well_posed_grey=G``, ``interior_shading=1``), prints per frame the soft coverage's area over the exact
mask's and its centroid minus the exact one's (``dx``, ``dy``, px), the same for the hard mask,
and the exact centroid. The exact masks are the frame's instant, so a blurred frame's coverage
differs from them by the blur's own asymmetry too (a few hundredths of a pixel at these speeds).
Written for HISTORY.md *Sixty-first session* (a clip's first frames over a dark cabinet).

``--dark``: over every recording of the set without a lens, each frame's coverage centroid error
(about the recording's median) against the share of its outline band (the exact mask dilated
and eroded by 4 px) whose background is ill-posed for the per-pixel fit (``|B| sin(angle(A, B))``
at most ``well_posed_grey``, 10 grey levels): frames pooled by that share, the RMS in x and y
and the fraction more than 0.6 px off in either.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
from true_masks import recording_parts

import torchfit.video as video
from torchfit.video import SegmentationSettings, load_observation, raw_moments

HERE = Path(__file__).resolve().parent


def centroids(moments: np.ndarray) -> np.ndarray:
    """(T, 2) centroids (x, y), px, of (T, 6) raw moments (each frame non-empty)."""
    return moments[:, 1:3] / moments[:, :1]


def frame_errors(folder: Path, **settings) -> dict:
    """The recording ``folder``'s per-frame errors: ``area`` (T,) coverage area / exact area,
    ``coverage`` and ``mask`` (T, 2) centroid offsets (px) of the soft coverage and the hard mask
    from the exact mask, ``exact`` (T, 2) the exact centroid (px). ``settings``: any
    :class:`SegmentationSettings` other than their defaults (one albedo pass always)."""
    _, _, camera = recording_parts(folder)
    observation = load_observation(str(folder / "video.mp4"), camera=camera,
                                   settings=SegmentationSettings(albedo_passes=1, **settings))
    exact = raw_moments(np.load(folder / "masks.npz")["masks"].astype(bool))
    coverage, mask = np.asarray(observation.coverage_moments), raw_moments(observation.masks)
    return {"area": coverage[:, 0] / exact[:, 0], "coverage": centroids(coverage) - centroids(exact),
            "mask": centroids(mask) - centroids(exact), "exact": centroids(exact)}


def dark_frames(folder: Path, **settings) -> tuple[np.ndarray, np.ndarray]:
    """The recording ``folder``'s (T, 2) coverage centroid errors (px, about their median) and (T,)
    share of each exact outline band (4 px either side) over background the per-pixel fit does not
    trust (read from the segmentation's own :func:`torchfit.video._background_terms`), segmented
    with ``settings`` (:func:`frame_errors`)."""
    kept = []
    original = video._background_terms

    def watching(background, albedo):
        terms = original(background, albedo)
        if background.ndim == 3:  # the whole image's, not the albedo pass's pixels
            kept.append(terms[2])
        return terms

    video._background_terms = watching
    try:
        error = frame_errors(folder, **settings)["coverage"]
    finally:
        video._background_terms = original
    ill = kept[-1] <= SegmentationSettings().well_posed_grey**2
    masks = np.load(folder / "masks.npz")["masks"].astype(bool)
    kernel = np.ones((9, 9), np.uint8)
    share = np.array([ill[(cv2.dilate(m.astype(np.uint8), kernel) > 0) & (cv2.erode(m.astype(np.uint8), kernel) == 0)].mean()
                      for m in masks])
    return error - np.median(error, 0), share


def dark_table(folder: Path, **settings) -> None:
    """Print :func:`dark_frames` pooled over the set ``folder``'s recordings without a lens."""
    names = [f.name for f in sorted(folder.iterdir()) if (f / "masks.npz").is_file() and not f.name.startswith("lens")]
    found = [dark_frames(folder / name, **settings) for name in names]
    error, share = np.concatenate([e for e, _ in found]), np.concatenate([s for _, s in found])
    print(f"{len(names)} recordings, {len(share)} frames; share of the outline band over ill-posed background:")
    for low, high in ((-1, 0), (0, 0.1), (0.1, 0.3), (0.3, 0.6), (0.6, 1)):
        chosen = (share > low) & (share <= high)
        if chosen.any():
            rms = np.sqrt((error[chosen] ** 2).mean(0))
            far = (np.abs(error[chosen]) > 0.6).any(1).mean()
            label = "none" if low < 0 else f"({low:g}, {high:g}]"
            print(f"  {label:>10}: {chosen.sum():4d} frames, centroid RMS x {rms[0]:.3f} y {rms[1]:.3f} px, "
                  f"{far:.1%} more than 0.6 px off")


SETTINGS = {"well_posed_grey": float, "interior_shading": lambda v: bool(int(v))}


def parsed_settings(pairs: list[str]) -> dict:
    """``SETTING=VALUE`` command-line pairs as :class:`SegmentationSettings` keywords (only
    those of ``SETTINGS``)."""
    found = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        if key not in SETTINGS:
            raise SystemExit(f"{pair!r}: expected one of {', '.join(f'{k}=VALUE' for k in SETTINGS)}")
        try:
            found[key] = SETTINGS[key](value)
        except ValueError:
            raise SystemExit(f"{pair!r}: {value!r} is not a value for {key}") from None
    return found


def main(argv: list[str]) -> None:
    pairs = [a for a in argv if "=" in a]
    settings, names = parsed_settings(pairs), [a for a in argv if a not in pairs]
    if len(names) == 2 and names[1] == "--dark":
        if not (HERE / names[0]).is_dir():
            raise SystemExit(f"{HERE / names[0]}: no set (make_concealed.py makes the sets)")
        dark_table(HERE / names[0], **settings)
        return
    if len(names) != 2:
        raise SystemExit("usage: coverage_frames.py SET NAME [SETTING=VALUE ...] | SET --dark [SETTING=VALUE ...]")
    folder = HERE / names[0] / names[1]
    if not (folder / "masks.npz").is_file():
        raise SystemExit(f"{folder}: no recording (make_concealed.py makes the sets)")
    found = frame_errors(folder, **settings)
    print("frame  area   coverage dx, dy   mask dx, dy   exact centroid")
    for t, (area, c, m, e) in enumerate(zip(found["area"], found["coverage"], found["mask"], found["exact"])):
        print(f"{t:5d}  {area:.3f}  {c[0]:+6.2f} {c[1]:+6.2f}   {m[0]:+6.2f} {m[1]:+6.2f}   ({e[0]:.0f}, {e[1]:.0f})")


if __name__ == "__main__":
    main(sys.argv[1:])
