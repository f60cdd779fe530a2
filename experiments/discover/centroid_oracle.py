"""Discover as the default runs it on video, with the soft coverage's centroid made exact on some frames.

    python experiments/discover/centroid_oracle.py SET NAME FIRST LAST OUT   # ~1-2 min

For one concealed recording (``SET``: a folder of recordings beside this file, e.g.
``recordings_fresh6``), frames ``FIRST..LAST`` (inclusive) keep the segmentation's area and
covariance but take the engine's exact mask's centroid; then discover runs with the default's
settings on video (the concealed table's: one albedo pass, the exposure fitted from 0.5 with a
camera's shutter, Huber's loss at 2, the held-out start and end, 12 final candidates, the jump
test with one neighbour), writing to ``OUT``. An empty range (``FIRST > LAST``) is the default
run itself. Which frames' centroid error moves a verdict or a held-out prediction? Prints the
verdict and each held-out part's centroid miss. Written for HISTORY.md *Sixty-first session*.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch
from concealed import VIDEO_SELECTION, recording_exposure
from true_masks import problem_of, recording_parts

from torchfit.discover_video import discover_video
from torchfit.losses import central_moments, raw_from_central
from torchfit.search import SearchSettings
from torchfit.video import SegmentationSettings, load_observation, raw_moments

HERE = Path(__file__).resolve().parent


def with_exact_centroids(moments: np.ndarray, exact: np.ndarray, first: int, last: int) -> np.ndarray:
    """(T, 6) raw ``moments`` whose frames ``first..last`` (inclusive) have the (T, 6) ``exact``
    moments' centroid, their own area and covariance; the rest as they are."""
    out = np.asarray(moments, np.float64).copy()
    span = slice(first, last + 1)
    area, _, cov = central_moments(torch.as_tensor(out[span]))
    _, centroid, _ = central_moments(torch.as_tensor(np.asarray(exact, np.float64)[span]))
    out[span] = raw_from_central(area, centroid, cov).numpy()
    return out


def run(folder: Path, first: int, last: int, out: Path) -> dict:
    """Discover's result (dict) on the recording ``folder`` with frames ``first..last``' centroids exact."""
    truth, shape, camera = recording_parts(folder)
    observation = load_observation(str(folder / "video.mp4"), camera=camera, settings=SegmentationSettings(albedo_passes=1))
    exact = raw_moments(np.load(folder / "masks.npz")["masks"].astype(bool))
    observation = dataclasses.replace(
        observation, coverage_moments=with_exact_centroids(observation.coverage_moments, exact, first, last))
    problem, span = problem_of(observation, shape, camera)
    return discover_video(problem, observation, span, settings=VIDEO_SELECTION, truth=truth, out_dir=out,
                          overlay=False, progress=lambda *_: None, exposure=recording_exposure(truth, 0.5, 0),
                          fit_exposure=True, robust=2.0, backcast=True, jump_neighbours=1,
                          search=SearchSettings(final=12))


def main(argv: list[str]) -> None:
    if len(argv) != 5:
        raise SystemExit("usage: centroid_oracle.py SET NAME FIRST LAST OUT")
    folder = HERE / argv[0] / argv[1]
    if not (folder / "masks.npz").is_file():
        raise SystemExit(f"{folder}: no recording (make_concealed.py makes the sets)")
    result = run(folder, int(argv[2]), int(argv[3]), Path(argv[4]))
    print("verdict:", result["verdict"])
    for part in result["located_heldout_after"]:
        channels = part["channels"]
        print(f"held-out frames {part['frames'][0]}-{part['frames'][1]}: " + ", ".join(
            f"{k} RMS {channels[k]['rms']:.2f} px, largest {channels[k]['largest']:.2f}" for k in ("centroid_x", "centroid_y")))


if __name__ == "__main__":
    main(sys.argv[1:])
