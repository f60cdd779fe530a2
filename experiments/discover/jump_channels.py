"""Which channel makes the jump test leave a frame out, at 6 jitter sigmas and at a stricter
threshold (HISTORY.md, *Forty-sixth session*).

    python experiments/discover/jump_channels.py [--sigmas 6 4] [--sets recordings recordings_fresh6 ...]

Reads ``results/diagnose_jump-scores_<set>_<name>.json`` (``diagnose.py jump-scores SET NAME...``)
and prints, per threshold, how many frames each channel leaves out (a frame counts once per
channel past the threshold), on controls and on effect recordings, at the clip's ends (its first
and last used frames) and inside; then each recording's frames that the stricter threshold adds,
with the channels that take them. Writes the counts to results/jump_channels.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
CHANNELS = ("centroid_x", "centroid_y", "scale", "shape", "orientation")


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


if __name__ == "__main__":
    main(sys.argv[1:])
