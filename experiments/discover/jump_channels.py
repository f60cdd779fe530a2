"""Which channel makes the jump test leave a frame out, at 6 jitter sigmas and at a stricter
threshold (HISTORY.md, *Forty-sixth session*).

    python experiments/discover/jump_channels.py [--sigmas 6 4] [--sets recordings recordings_fresh6 ...] [--one-at-a-time] [--neighbours K]

Reads ``results/diagnose_jump-scores_<set>_<name>.json`` (``diagnose.py jump-scores SET NAME...``)
and prints, per threshold, how many frames each channel leaves out (a frame counts once per
channel past the threshold), on controls and on effect recordings, at the clip's ends (its first
and last used frames) and inside; then each recording's frames that the stricter threshold adds,
with the channels that take them. Writes the counts to results/jump_channels.json. With
``--one-at-a-time`` and/or ``--neighbours K``, the frames ``jump_outliers`` leaves out so (one at
a time; with the K frames on either side of each) against at once, and the runs whose frames that
changes (results/jump_one_at_a_time.json, jump_neighbours<K>.json, jump_one_at_a_time_neighbours<K>.json).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from torchfit.discover_video import JUMP_SIGMAS, jump_outliers
from torchfit.residuals import CHANNELS

HERE = Path(__file__).resolve().parent


def past(row: dict, sigmas: float) -> dict[int, list[str]]:
    """The recording's frames (video numbers) past ``sigmas`` in some channel, with those channels."""
    out: dict[int, list[str]] = {}
    for name, scores in row["scores"].items():
        for frame, score in zip(row["frames"], scores):
            if score is not None and score > sigmas:
                out.setdefault(frame, []).append(name)
    return out


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sigmas", type=float, nargs="+", default=[6.0, 4.0])
    parser.add_argument("--sets", nargs="+", default=None, help="set folders (default: every one with scores)")
    parser.add_argument("--one-at-a-time", action="store_true",
                        help="also the frames left out one at a time, and the runs that changes "
                             "(results/jump_one_at_a_time.json)")
    parser.add_argument("--neighbours", type=int, default=0, metavar="K",
                        help="also the frames left out with the K frames on either side of each, and the runs "
                             "that changes (results/jump_neighbours<K>.json)")
    parser.add_argument("--default", default="_albedo1_exposure0.5_taps0_fitted_huber2_backcast_final12",
                        help="the stored runs with no neighbour left out (the default before the forty-seventh "
                             "session), against whose frames the frames at once are checked")
    args = parser.parse_args(argv)
    files = sorted((HERE / "results").glob("diagnose_jump-scores_*.json"))
    rows = {}
    for file in files:
        stem = file.stem[len("diagnose_jump-scores_"):]
        for name in ("recordings_fresh" + str(k) for k in range(1, 10)):
            if stem.startswith(name + "_"):
                key = (name, stem[len(name) + 1:])
                break
        else:
            key = ("recordings", stem[len("recordings_"):])
        if args.sets is None or key[0] in args.sets:
            rows[key] = json.loads(file.read_text())
    if not rows:
        sys.exit("no results/diagnose_jump-scores_*.json: run diagnose.py jump-scores SET NAME... first")
    counts = {}
    for sigmas in args.sigmas:
        table = {group: {where: {c: 0 for c in CHANNELS} | {"frames": 0, "runs": 0} for where in ("ends", "inside")}
                 for group in ("controls", "effects")}
        for (set_name, name), row in rows.items():
            group = "controls" if name.startswith("control") else "effects"
            used = [f for f, s in zip(row["frames"], row["scores"]["centroid_x"]) if s is not None]
            ends = {used[0], used[-1]} if used else set()
            hit = past(row, sigmas)
            for where in ("ends", "inside"):
                frames = {f: c for f, c in hit.items() if (f in ends) == (where == "ends")}
                table[group][where]["frames"] += len(frames)
                table[group][where]["runs"] += bool(frames)
                for channels in frames.values():
                    for c in channels:
                        table[group][where][c] += 1
        counts[f"{sigmas:g}"] = table
        print(f"\n== past {sigmas:g} sigmas ({len(rows)} recordings): frames per channel")
        print(f"{'':20s} {'frames':>6s} {'runs':>5s} " + " ".join(f"{c:>11s}" for c in CHANNELS))
        for group, wheres in table.items():
            for where, cells in wheres.items():
                print(f"{group + ' ' + where:20s} {cells['frames']:6d} {cells['runs']:5d} "
                      + " ".join(f"{cells[c]:11d}" for c in CHANNELS))
    if len(args.sigmas) > 1:
        low, high = min(args.sigmas), max(args.sigmas)
        print(f"\n== frames past {low:g} but not {high:g} sigmas, per recording: channels (score)")
        for (set_name, name), row in sorted(rows.items()):
            added = sorted(set(past(row, low)) - set(past(row, high)))
            if added:
                parts = []
                for frame in added:
                    k = row["frames"].index(frame)
                    parts.append(f"{frame}: " + ", ".join(f"{c} {row['scores'][c][k]:.1f}" for c in CHANNELS
                                                          if c in row["scores"] and row["scores"][c][k] is not None
                                                          and row["scores"][c][k] > low))
                print(f"{set_name:20s} {name:22s} " + "; ".join(parts))
    (HERE / "results" / "jump_channels.json").write_text(json.dumps(counts, indent=1))
    if args.one_at_a_time or args.neighbours:
        changed = against_at_once(rows, args.sigmas, args.default, args.one_at_a_time, args.neighbours)
        name = "_".join((["one_at_a_time"] if args.one_at_a_time else [])
                        + ([f"neighbours{args.neighbours}"] if args.neighbours else []))
        (HERE / "results" / f"jump_{name}.json").write_text(json.dumps(changed, indent=1))


def against_at_once(rows: dict, thresholds: list[float], default: str, one_at_a_time: bool,
                    neighbours: int) -> dict:
    """Per threshold, the frames ``jump_outliers`` leaves out at once and as the candidate does
    (``one_at_a_time``, ``neighbours``) from the stored channels, checked at once against the
    stored runs' ``outlier_frames`` (at 6 sigmas the default's results folder ``default``, at
    another S its ``_jump<S>``; a stored run missing is not checked), and the recordings whose
    frames the candidate changes."""
    label = " and ".join((["one at a time"] if one_at_a_time else [])
                         + ([f"with {neighbours} neighbour(s) each side"] if neighbours else []))
    out = {}
    for sigmas in thresholds:
        suffix = default + ("" if sigmas == JUMP_SIGMAS else f"_jump{sigmas:g}")
        changed, checked, frames_at_once, frames_one = [], 0, 0, 0
        for (set_name, name), row in sorted(rows.items()):
            if "values" not in row:
                sys.exit(f"{set_name}/{name}: its scores were stored without the channels; run diagnose.py "
                         "jump-scores on it again")
            used = np.array([v is not None for v in row["values"]["centroid_x"]])
            frames = np.array(row["frames"])[used]
            values = {c: np.array([v for v in row["values"][c] if v is not None], dtype=float) for c in CHANNELS}
            at_once = [int(f) for f in frames[jump_outliers(values, sigmas)[0]]]
            one = [int(f) for f in frames[jump_outliers(values, sigmas, one_at_a_time, neighbours)[0]]]
            fresh = set_name.removeprefix("recordings")
            stored = HERE / "results" / f"concealed{fresh}{suffix}" / name / "discover.json"
            if stored.exists():
                kept = json.loads(stored.read_text())["outlier_frames"]
                if kept != at_once:
                    sys.exit(f"{set_name}/{name} at {sigmas:g}: at once {at_once}, stored {kept}: the channels "
                             "do not reproduce the stored run")
                checked += 1
            frames_at_once, frames_one = frames_at_once + len(at_once), frames_one + len(one)
            if one != at_once:
                changed.append({"set": set_name, "name": name, "at_once": at_once, "candidate": one})
        print(f"\n== {sigmas:g} sigmas: {len(changed)} of {len(rows)} runs change {label} "
              f"({frames_at_once} frames left out at once, {frames_one} {label}; "
              f"{checked} stored runs reproduced at once)")
        for row in changed:
            print(f"{row['set']:20s} {row['name']:22s} at once {row['at_once']}  {label} {row['candidate']}")
        out[f"{sigmas:g}"] = changed
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
