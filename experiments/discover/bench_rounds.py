"""Benchmark: a round of discover's candidate refits one at a time against side by side.

Every round of discover refits the model with each candidate effect added, on all frames and
on each held-out split's train frames (three fits per candidate with the default backcast).
``VideoProblem.fit_many`` runs all of a round's fits in lockstep, so each Levenberg-Marquardt
iteration integrates and renders all of them in one batch. This script times, on one recording
after one shared baseline, the same round three ways: each fit alone, one after the other (as
discover ran until 2026-11-29); one candidate's fits side by side, candidate after candidate
(``VideoProblem.fit``); all of them side by side (``fit_many``, what discover runs). And it checks
that they end in the same place.

    python experiments/discover/bench_rounds.py                        # the shipped T-handle, default settings
    python experiments/discover/bench_rounds.py --recording experiments/discover/recordings_fresh2/control_tshape
    python experiments/discover/bench_rounds.py --quick --repeats 1 --out /tmp/q.json   # two candidates, 2 iterations (the test)

Prints the figures and writes JSON (default ``experiments/discover/results/bench_rounds.json``).
Times on shared machines are noisy: read the ratios, measured in one process, the ways in turn
(``--repeats``, medians).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # true_masks.py, concealed.py

from concealed import recording_exposure  # noqa: E402
from true_masks import load_problem, recording_parts  # noqa: E402

import torchfit  # noqa: E402
from torchfit.discover_video import DEFAULT_CANDIDATES, VideoProblem  # noqa: E402
from torchfit.run import robust_setting  # noqa: E402
from torchfit.video import SegmentationSettings  # noqa: E402

SHIPPED = Path(torchfit.__file__).resolve().parent / "recordings" / "tshape"
DEFAULT_OUT = HERE / "results" / "bench_rounds.json"
QUICK_CANDIDATES = ("quadratic_drag", "time_scale")


def _fits_agree(alone, together) -> dict:
    """Largest differences between two lists of ModelFits of the same models: chi-squared (its
    value, so a BIC difference), held-out RMS (noise units) and the effects' parameters
    (relative to the larger of the value and 1e-3)."""
    chi2 = max(abs(a.rss - b.rss) for a, b in zip(alone, together))
    heldout = max(abs(a.heldout_rms - b.heldout_rms) for a, b in zip(alone, together))
    params = 0.0
    for a, b in zip(alone, together):
        for name, entries in a.params.items():
            for pname, entry in entries.items():
                x = torch.as_tensor(entry["value"], dtype=torch.float64)
                y = torch.as_tensor(b.params[name][pname]["value"], dtype=torch.float64)
                params = max(params, float(((x - y).abs() / x.abs().clamp(min=1e-3)).max()))
    return {"chi2": chi2, "heldout_rms": heldout, "params_relative": params}


def _each_alone(video: VideoProblem, effects: tuple[str, ...], warm):
    """``video.fit(effects, warm)`` as it ran before ``fit_many`` (2026-11-29): the all-frames fit,
    then each split's, one after the other, each screened and refitted on its own."""
    everything = video.problem.used.cpu().numpy().astype(bool)
    new = tuple(name for name in effects if name not in warm.payload["model"].values)
    _, screened = video._screen(video._extend(warm.payload["model"], effects), new, everything)
    run = video._lm(screened, everything, video.iterations)
    helds = []
    for (train, _), warm_held in zip(video.splits, warm.payload["held_models"]):
        _, held_screened = video._screen(video._extend(warm_held, effects), new, train)
        helds.append(video._lm(held_screened, train, video.iterations))
    return video._scored(effects, run, helds)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recording", type=Path, default=SHIPPED,
                        help="a recording folder (video.mp4, truth.json, mesh.obj, camera.json)")
    parser.add_argument("--quick", action="store_true", help=f"candidates {QUICK_CANDIDATES}, 2 iterations")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--repeats", type=int, default=2,
                        help="times each way runs, in turn, the order reversed every other time; medians reported")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be at least 1, got {args.repeats}")
    if not (args.recording / "video.mp4").is_file():
        parser.error(f"--recording must be a recording folder holding video.mp4, got {args.recording}")

    # the default path as concealed.py's default-equivalent runs load it (its recording_parts: the
    # shape from truth.json): one albedo pass, the exposure fitted from 0.5 with a camera's rule,
    # Huber's loss at 2 noise units, the first and the last quarter held out
    truth, shape, camera = recording_parts(args.recording)
    observation, problem, span = load_problem(args.recording, shape, camera, False,
                                              SegmentationSettings(albedo_passes=1))
    exposure = recording_exposure(truth, 0.5, 0)
    coverage = torch.as_tensor(observation.coverage_moments[span])
    candidates = QUICK_CANDIDATES if args.quick else tuple(DEFAULT_CANDIDATES)
    video = VideoProblem(problem, candidates=candidates, iterations=2 if args.quick else 15, exposure=exposure,
                         coverage=coverage, fit_exposure=True, robust=robust_setting(None, exposure), backcast=True,
                         progress=print)
    clock = time.perf_counter()
    base = video.fit((), None)
    baseline_s = time.perf_counter() - clock
    sets = [(name,) for name in candidates]
    ways = {"side_by_side": lambda: video.fit_many(sets, base),
            "one_candidate_at_a_time": lambda: [video.fit(effects, base) for effects in sets],
            "each_fit_alone": lambda: [_each_alone(video, effects, base) for effects in sets]}
    seconds, fits = {way: [] for way in ways}, {}
    for repeat in range(args.repeats):  # the ways in turn, the order reversed on every other repeat
        for way in (list(ways) if repeat % 2 == 0 else list(ways)[::-1]):
            clock = time.perf_counter()
            fits[way] = ways[way]()
            seconds[way].append(time.perf_counter() - clock)
    each_s, alone_s, together_s = (statistics.median(seconds[way]) for way in
                                   ("each_fit_alone", "one_candidate_at_a_time", "side_by_side"))
    each, alone, together = fits["each_fit_alone"], fits["one_candidate_at_a_time"], fits["side_by_side"]

    result = {
        "env": {"torch": torch.__version__, "threads": torch.get_num_threads(), "cpus": os.cpu_count(),
                "machine": platform.machine(), "date": _dt.datetime.now().isoformat(timespec="seconds")},
        "config": {"recording": str(args.recording), "candidates": list(candidates), "quick": args.quick,
                   "iterations": video.iterations, "splits": len(video.splits)},
        "baseline_s": baseline_s,
        "round": {"fits": len(sets) * (1 + len(video.splits)), "repeats": args.repeats, "seconds": seconds,
                  "each_fit_alone_s": each_s,
                  "one_candidate_at_a_time_s": alone_s, "side_by_side_s": together_s,
                  "speedup": each_s / together_s, "speedup_over_one_candidate_at_a_time": alone_s / together_s},
        "largest_difference": _fits_agree(each, together),
        "largest_difference_one_candidate_at_a_time": _fits_agree(alone, together),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    r = result["round"]
    print(f"{args.recording.name}: baseline {baseline_s:.1f} s; a round of {len(sets)} candidates ({r['fits']} fits): "
          f"each fit alone {each_s:.1f} s, one candidate's fits at a time {alone_s:.1f} s, all side by side "
          f"{together_s:.1f} s: {r['speedup']:.2f}x and {r['speedup_over_one_candidate_at_a_time']:.2f}x")
    d = result["largest_difference"]
    print(f"largest difference: chi2 {d['chi2']:.2e}, held-out RMS {d['heldout_rms']:.2e} noise units, "
          f"parameters {d['params_relative']:.2e} relative; written to {args.out}")
    assert all(math.isfinite(v) for v in d.values())
    return result


if __name__ == "__main__":
    main()
