"""The segmentation's error against the noise model: its size over the run's floors, and how long it lasts.

For each recording: the segmented masks (the default segmentation) against MuJoCo's true masks,
frame by frame: centroid x and y (px) and scale (the relative error of sqrt(area)). Printed per
channel: RMS / the run's noise floor (``discover.json``'s ``noise``, the floors estimated from the
baseline's residuals: a robust jitter), the error's own robust spread (1.4826 MAD) / floor, mean / floor, and the error's autocorrelation at lags 1, 2, 3 and 5 (an AR(1)
error with lag-1 correlation r has r^k at lag k). Needs the recordings
(``make_concealed.py [--fresh K] [--sharp]``) and the runs whose floors it reads
(``concealed.py [--fresh K] ...``, the folder ``results/concealed[_fresh<K>]<SUFFIX>``).

``--coverage`` compares the soft coverage's moments (``Observation.coverage_moments``, what the
exposure path fits; segmented with ``--albedo-passes`` passes) instead of the binary masks'. The
engine's masks are the instant's, so on blurred video this counts the blur's own averaging as
error; on a set made without blur (``--sharp``) the two are alike.

    python experiments/discover/segmentation_correlation.py [--fresh K] [names...]   # ~15 s per recording
    python experiments/discover/segmentation_correlation.py --fresh 4 --sharp --coverage --albedo-passes 1 \
        --runs _albedo1_exposure0.5_taps0_fitted_huber2_backcast_edge0.05_final12_nb1_sharp
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from true_masks import both_frames

from torchfit.video import SegmentationSettings, load_observation, raw_moments

HERE = Path(__file__).resolve().parent
CHANNELS = ("centroid_x", "centroid_y", "scale")
LAGS = (1, 2, 3, 5)


def autocorrelation(error: np.ndarray, lag: int) -> float:
    """Sample autocorrelation of a (T,) series at ``lag`` (about its mean)."""
    e = error - error.mean()
    return float((e[:-lag] * e[lag:]).sum() / (e * e).sum())


def moment_errors(segmented: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(F, 3) centroid x, y (px) and relative sqrt-area errors of (T, 6) raw moments (the
    segmentation's masks' or coverage's) against those of the (T, H, W) bool true masks, over the
    F frames where both are non-empty ((0,) when there is none); the true masks' moments from the
    segmentation's own :func:`torchfit.video.raw_moments`."""
    ref = raw_moments(true)
    both = both_frames(segmented, ref)
    if not len(both):
        return np.empty(0)
    seg, ref = segmented[both], ref[both]
    return np.stack((seg[:, 1] / seg[:, 0] - ref[:, 1] / ref[:, 0], seg[:, 2] / seg[:, 0] - ref[:, 2] / ref[:, 0],
                     np.sqrt(seg[:, 0] / ref[:, 0]) - 1.0), axis=-1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", help="recordings (default: all of the set)")
    ap.add_argument("--fresh", type=int, default=0, metavar="K", help="fresh set K (0: the first)")
    ap.add_argument("--sharp", action="store_true", help="the set made without motion blur (make_concealed.py --sharp)")
    ap.add_argument("--runs", default="", metavar="SUFFIX",
                    help="the runs' folder suffix after concealed[_fresh<K>] (default: none, the masks' runs)")
    ap.add_argument("--coverage", action="store_true", help="the soft coverage's moments, not the binary masks'")
    ap.add_argument("--albedo-passes", type=int, default=None, help="the segmentation's albedo passes")
    args = ap.parse_args(argv)
    if args.fresh < 0:
        ap.error(f"--fresh needs a set number K >= 0, got {args.fresh}")
    suffix = f"_fresh{args.fresh}" if args.fresh else ""
    recordings = HERE / f"recordings{suffix}{'_sharp' if args.sharp else ''}"
    results = HERE / "results" / f"concealed{suffix}{args.runs}"
    if not recordings.is_dir():
        raise SystemExit(f"no recordings {recordings} (make_concealed.py{' --fresh ' + str(args.fresh) if args.fresh else ''}"
                         f"{' --sharp' if args.sharp else ''})")
    settings = SegmentationSettings() if args.albedo_passes is None else SegmentationSettings(albedo_passes=args.albedo_passes)
    names = args.names or sorted(p.name for p in recordings.iterdir() if (p / "masks.npz").exists())
    for name in names:
        run = results / name / "discover.json"
        if not run.exists():
            raise SystemExit(f"no run {run} (concealed.py{' --fresh ' + str(args.fresh) if args.fresh else ''} ... {name})")
        floors = json.loads(run.read_text())["noise"]
        folder = recordings / name
        observation = load_observation(folder / "video.mp4", camera=folder / "camera.json", settings=settings)
        moments = observation.coverage_moments if args.coverage else raw_moments(np.asarray(observation.masks, bool))
        errors = moment_errors(moments, np.load(folder / "masks.npz")["masks"])
        cells = []
        for channel, error in zip(CHANNELS, errors.T):
            floor = floors[channel]
            robust = 1.4826 * np.median(np.abs(error - np.median(error)))  # as the floor's own MAD
            cells.append(f"{channel} rms/floor {np.sqrt((error ** 2).mean()) / floor:4.2f} mad/floor {robust / floor:4.2f} "
                         f"mean/floor {error.mean() / floor:+5.2f} acf "
                         + " ".join(f"{autocorrelation(error, k):+.2f}" for k in LAGS))
        print(f"{name:16s} " + " | ".join(cells), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
