"""Two results trees of the same runs side by side: verdicts, and how far every score moved.

For every ``discover.json`` found under both ``FIRST`` and ``SECOND`` at the same relative path
(``results/concealed<set><suffix>/<recording>/discover.json``, as ``concealed.py`` writes them):
whether the verdict is the same, the largest change of any candidate's ΔBIC in any round both
runs scored, and whether the report's line on the held-out predictions (``located_heldout``, the
baseline's, and ``located_heldout_after``, the final model's) flags a channel in each. Prints the
recordings whose verdict differs (with both verdicts), the largest ΔBIC changes, a summary line,
and how many runs' predictions' lines flag a channel in each tree, on the controls (no hidden
effect) and on the recordings named right; ``--out FILE`` also writes it all as JSON.

    python experiments/discover/compare_runs.py /tmp/frozen/experiments/discover/results experiments/discover/results

Made to check a rerun of stored runs (HISTORY.md, *Fortieth session*): a rerun of the same
recordings with code that changes no fit should give the same verdicts and ΔBICs within the
machine's rounding. The predictions' lines were compared for the fifty-sixth session's change of
their test.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path


def score_changes(first: dict, second: dict) -> list[tuple[float, str, int]]:
    """``(|ΔBIC change|, candidate, round)`` for every candidate and round both runs
    (``discover.json`` contents) scored, largest first."""
    out = []
    for name, rounds in first["effects"].items():
        for k, (a, b) in enumerate(zip(rounds, second["effects"].get(name, []))):
            x, y = a.get("delta_bic"), b.get("delta_bic")
            if x is not None and y is not None and math.isfinite(x) and math.isfinite(y):
                out.append((abs(x - y), name, k))
    return sorted(out, reverse=True)


def predictions_flag(content: dict, key: str) -> bool:
    """Whether a run's (``discover.json`` contents) line on its held-out predictions, ``key``
    ``located_heldout`` (the baseline's) or ``located_heldout_after`` (the final model's), flags a
    channel in any held-out part."""
    return any(part["flagged"] for part in content.get(key) or [])


def compare(first_root: Path, second_root: Path) -> dict:
    """``{"runs": [...], "differ": [...], "largest": ...}`` over the runs under both roots."""
    runs = []
    for path in sorted(first_root.glob("*/*/discover.json")):
        other = second_root / path.relative_to(first_root)
        if not other.exists():
            continue
        a, b = json.loads(path.read_text()), json.loads(other.read_text())
        changes = score_changes(a, b)
        runs.append({"run": str(path.parent.relative_to(first_root)), "verdict_first": a["verdict"],
                     "verdict_second": b["verdict"], "same_verdict": a["verdict"] == b["verdict"]
                     and a.get("indistinguishable") == b.get("indistinguishable"),
                     "largest_delta_bic_change": changes[0][0] if changes else 0.0,
                     "where": list(changes[0][1:]) if changes else None,
                     "control": not a.get("truth_effects"),
                     "right": bool(a.get("truth_effects")) and sorted(a["verdict"]) == sorted(a["truth_effects"]),
                     "flags": {key: [predictions_flag(a, key), predictions_flag(b, key)]
                               for key in ("located_heldout", "located_heldout_after")}})
    return {"runs": runs, "differ": [r for r in runs if not r["same_verdict"]],
            "largest": sorted(runs, key=lambda r: -r["largest_delta_bic_change"])[:10]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("first", type=Path, help="a results folder (holding concealed*/<recording>/discover.json)")
    ap.add_argument("second", type=Path, help="another, with runs of the same recordings")
    ap.add_argument("--out", type=Path, help="also write the comparison as JSON here")
    args = ap.parse_args(argv)
    for root in (args.first, args.second):
        if not root.is_dir():
            ap.error(f"not a folder: {root}")
    result = compare(args.first, args.second)
    if not result["runs"]:
        ap.error(f"no run is under both {args.first} and {args.second}")
    for r in result["differ"]:
        print(f"verdict differs: {r['run']}: {r['verdict_first']} against {r['verdict_second']}")
    for r in result["largest"]:
        print(f"{r['run']}: ΔBIC moved by up to {r['largest_delta_bic_change']:.3g} ({r['where'][0]}, round {r['where'][1]})"
              if r["where"] else f"{r['run']}: no score in common")
    print(f"{len(result['runs'])} runs in both; {len(result['differ'])} verdicts differ; every ΔBIC within "
          f"{max(r['largest_delta_bic_change'] for r in result['runs']):.3g}")
    for label, group in (("controls", [r for r in result["runs"] if r["control"]]),
                         ("named right (first tree)", [r for r in result["runs"] if r["right"]])):
        counts = {key: [sum(r["flags"][key][i] for r in group) for i in (0, 1)]
                  for key in ("located_heldout", "located_heldout_after")}
        print(f"{label}, {len(group)} runs: the baseline's predictions flag a channel on "
              f"{counts['located_heldout'][0]} (first) and {counts['located_heldout'][1]} (second); the final "
              f"model's on {counts['located_heldout_after'][0]} and {counts['located_heldout_after'][1]}")
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
