"""Does a run's own detection limit say whether it names the hidden effect?

Every discover run reports, for each effect it did not name, the size below which that effect
would not have passed its criterion on this clip ("What this clip cannot rule out",
``detectable_above`` in discover.json, from the first round, before any name). On the concealed
recordings the truth is known, so the limit can be checked: for every effect case hiding one
effect of one scalar parameter (a drag or lift coefficient, a clock), the true departure from the
null over the run's limit (``concealed.limit_ratio``), against whether the run named exactly that
effect. A limit that is right names nearly everything above 1 and little below it; one that is too
cautious names much below 1; one that flatters the data misses much above it. From the stored
discover.json files (no fitting).

    python experiments/discover/limits.py SUFFIX [--fresh K ...] [--each]

``SUFFIX`` picks the results folders ``results/concealed<set><SUFFIX>`` ('' for the masks path);
the six sets unless ``--fresh`` names others (0 the first); ``--each`` lists every recording.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # concealed.py imports true_masks from its folder

from concealed import RECORDINGS, limit_ratio, row  # noqa: E402

SIX = (0, 1, 2, 3, 4, 5)
# the ratio's bins (true departure / the run's limit), each [low, high)
BINS = ((0.0, 0.5), (0.5, 1.0), (1.0, 1.5), (1.5, 2.0), (2.0, float("inf")))


def cases(content: dict, name: str, recordings: Path) -> tuple[float, bool] | None:
    """``(ratio, named right)`` for a run's discover.json ``content`` (recording ``name`` in the
    set folder ``recordings``), or None when no single scalar effect is hidden (a control, a
    lens, an offset)."""
    r = row(name, content, recordings)
    ratio = limit_ratio(r)
    return None if ratio is None else (ratio, r["right"])


def tally(pairs: list[tuple[float, bool]]) -> list[tuple[str, int, int]]:
    """Per bin of :data:`BINS`, then below 1 and at or above 1: ``(label, cases, named right)``."""
    def count(low: float, high: float) -> tuple[int, int]:
        inside = [right for ratio, right in pairs if low <= ratio < high]
        return len(inside), sum(inside)

    out = [(f"{low:g}–{high:g}" if high != float("inf") else f"≥ {low:g}", *count(low, high)) for low, high in BINS]
    return out + [("**below 1**", *count(0.0, 1.0)), ("**1 or above**", *count(1.0, float("inf")))]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("suffix", help="results folder suffix ('' for the masks path)")
    ap.add_argument("--fresh", type=int, nargs="+", metavar="K", help="these sets instead of the six (0 the first)")
    ap.add_argument("--each", action="store_true", help="list every recording's ratio and whether it was named")
    args = ap.parse_args(argv)
    pairs = []
    for k in args.fresh if args.fresh is not None else SIX:
        folder = HERE / "results" / f"concealed{f'_fresh{k}' if k else ''}{args.suffix}"
        if not folder.is_dir():
            raise SystemExit(f"no results folder {folder} (run concealed.py for that set and suffix first)")
        recordings = RECORDINGS.parent / f"{RECORDINGS.name}{f'_fresh{k}' if k else ''}"
        for path in sorted(folder.glob("*/discover.json")):
            case = cases(json.loads(path.read_text()), path.parent.name, recordings)
            if case is None:
                continue
            pairs.append(case)
            if args.each:
                print(f"{folder.name:52s} {path.parent.name:16s} truth / limit {case[0]:5.2f}  "
                      f"{'named' if case[1] else 'not named'}")
    print("| truth / the run's own limit | effect cases | named right |\n|---|---|---|")
    for label, n, right in tally(pairs):
        print(f"| {label} | {n} | {right} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
