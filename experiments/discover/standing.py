"""Where discover stands on the concealed sets: targets, how each case ended, and its own limits.

From the stored runs of one variant (no fitting), over the sets asked for:

1. per set, the issue's targets (``concealed.score``): effect cases named right, controls quiet,
   recordings with a name not hidden, held-out error halved on the right names, drag and lift
   coefficients within 25 % of the engine's;
2. how each effect case ended (``concealed.outcome``): named right, a tie that holds the truth,
   nothing named below the clip's own limit, nothing named above it, withheld, a wrong name;
3. the verdict grid, every recording against every set;
4. whether each run's own detection limit says what it names. Every run reports, for each
   effect it did not name, the size below which that effect would not have passed its criterion
   on this clip ("What this clip cannot rule out", ``detectable_above``, from the first round,
   before any name). For every case hiding one effect of one scalar parameter (a drag or lift
   coefficient, a clock), the true departure from the null over that limit
   (``concealed.limit_ratio``) against whether the run named exactly that effect. A limit that is
   right names nearly everything above 1 and little below; one too cautious names much below 1;
   one that flatters the data misses much above it;
5. where the report located a miss (``concealed.flagged``): the baseline's fit to all frames, its
   predictions of the held-out parts, and the final model's, by how each recording ended;
6. the exposure each baseline fitted (a nuisance; the recordings' own is half the frame
   interval): its median, quartiles and range, and the runs where it reached its bound, the whole
   interval (on runs that fit one); and the runs that left frames out as segmentation failures
   (``outlier_frames``);
7. with ``--beside OTHER``, another variant's runs of the same sets side by side: right names
   and quiet controls of each, the recordings whose outcome differs, and by how much the other's
   detection limits are lower.

    python experiments/discover/standing.py SUFFIX [--fresh K ...] [--each] [--beside OTHER]

``SUFFIX`` picks the results folders ``results/concealed<set><SUFFIX>``
(``_albedo1_exposure0.5_taps0_fitted_interior_huber2_backcast_final12_nb1`` for the default,
``_albedo1_exposure0.5_taps0_fitted_huber2_backcast_final12_nb1`` for it without the interior shading (before the
sixty-fourth session), ``_albedo1_exposure0.5_taps0_fitted_huber2_backcast_final12`` without the jump's neighbours,
``_albedo1_exposure0.5_taps0_fitted_huber2_backcast`` for it with the search's ``final=6`` of
before 2026-11-29, ``_albedo1_exposure0.5_taps0_fitted_huber2`` without the backcast, '' for the masks); the seven
blurred sets (the first and fresh 1-6) unless ``--fresh`` names others (0 the first); ``--each``
lists every scalar case's ratio.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # concealed.py imports true_masks from its folder

from concealed import grid_word, halved, limit_ratio, outcomes, row, score, verdict_grid  # noqa: E402
from true_masks import fresh_folder  # noqa: E402

SEVEN = (0, 1, 2, 3, 4, 5, 6)
DEFAULT_SUFFIX = "_albedo1_exposure0.5_taps0_fitted_interior_huber2_backcast_final12_nb1"  # the interior shading since the 64th session
# the ratio's bins (true departure / the run's limit), each [low, high)
BINS = ((0.0, 0.5), (0.5, 1.0), (1.0, 1.5), (1.5, 2.0), (2.0, float("inf")))


def cases(r: dict) -> tuple[float, bool] | None:
    """``(truth / the run's limit, named right)`` of a recording's ``concealed.row``, or None
    when no single scalar effect is hidden (a control, a lens, an offset)."""
    ratio = limit_ratio(r)
    return None if ratio is None else (ratio, r["right"])


def tally(pairs: list[tuple[float, bool]]) -> list[tuple[str, int, int]]:
    """Per bin of :data:`BINS`, then below 1 and at or above 1: ``(label, cases, named right)``."""
    def count(low: float, high: float) -> tuple[int, int]:
        inside = [right for ratio, right in pairs if low <= ratio < high]
        return len(inside), sum(inside)

    out = [(f"{low:g}–{high:g}" if high != float("inf") else f"≥ {low:g}", *count(low, high)) for low, high in BINS]
    return out + [("**below 1**", *count(0.0, 1.0)), ("**1 or above**", *count(1.0, float("inf")))]


def runs(suffix: str, sets: tuple[int, ...], results: Path = HERE / "results") -> dict:
    """``{set label: {recording: concealed.row}}`` from each set's stored discover.json files."""
    out = {}
    for k in sets:
        folder = results / f"concealed{f'_fresh{k}' if k else ''}{suffix}"
        if not folder.is_dir():
            raise SystemExit(f"no results folder {folder} (run concealed.py for that set and suffix first)")
        out[f"fresh {k}" if k else "first"] = {
            path.parent.name: row(path.parent.name, json.loads(path.read_text()), fresh_folder(k))
            for path in sorted(folder.glob("*/discover.json"))}
    return out


def targets(by_set: dict) -> str:
    """Table 1: the issue's targets per set and over all (``concealed.score``)."""
    lines = ["| set | right | controls quiet | wrong names | held-out halved | coefficients within 25 % |",
             "|---|---|---|---|---|---|"]
    every = [r for rows in by_set.values() for r in rows.values()]
    for label, rows in [*((label, list(rows.values())) for label, rows in by_set.items()), ("**all**", every)]:
        c = score(rows)
        lines.append(f"| {label} | {c['effect_right'][0]} of {c['effect_right'][1]} | {c['controls_quiet'][0]} of "
                     f"{c['controls_quiet'][1]} | {', '.join(c['wrong_names']) or 'none'} | {c['heldout_halved'][0]} of "
                     f"{c['heldout_halved'][1]} | {c['coefficients_within_25pc'][0]} of {c['coefficients_within_25pc'][1]} |")
    return "\n".join(lines)


def exposure_line(by_set: dict) -> str:
    """Line 6: the baselines' fitted exposure (``concealed.row``'s ``exposure_baseline``, a fraction
    of the frame interval) over every run that fitted one, and the runs at its bound of 1."""
    fitted = [(label, name, r["exposure_baseline"]["value"]) for label, rows in by_set.items()
              for name, r in rows.items() if r.get("exposure_baseline")]
    if not fitted:
        return "No run fitted the exposure."
    values = np.array([v for *_, v in fitted])
    at_bound = [f"{label} {name}" for label, name, v in fitted if v >= 0.99]
    q1, median, q3 = np.percentile(values, [25, 50, 75])
    return (f"The baselines' fitted exposure (of the frame interval; the recordings' 0.5), {len(values)} runs: "
            f"median {median:.3f}, quartiles {q1:.3f}–{q3:.3f}, range {values.min():.3f}–{values.max():.3f}; "
            f"at its bound (0.99 or more) on {len(at_bound)}" + (f": {', '.join(at_bound)}." if at_bound else "."))


def outlier_line(by_set: dict) -> str:
    """Line 6's second part: the runs that left frames out as segmentation failures, and how many."""
    rows = [r for rows in by_set.values() for r in rows.values()]
    left = [len(r.get("outlier_frames", [])) for r in rows]
    return (f"Frames left out as segmentation failures: on {sum(n > 0 for n in left)} of {len(rows)} runs, "
            f"{sum(left)} frames in all.")


def limits_table(by_set: dict, each: bool = False) -> str:
    """Table 4: :func:`tally` over every scalar case (with ``each``, every case's line first)."""
    lines, pairs = [], []
    for label, rows in by_set.items():
        for name, r in rows.items():
            case = cases(r)
            if case is not None:
                pairs.append(case)
                if each:
                    lines.append(f"{label:8s} {name:16s} truth / limit {case[0]:5.2f}  "
                                 f"{'named' if case[1] else 'not named'}")
    lines += ["| truth / the run's own limit | effect cases | named right |", "|---|---|---|"]
    lines += [f"| {label} | {n} | {right} |" for label, n, right in tally(pairs)]
    return "\n".join(lines)


def located_table(by_set: dict) -> str:
    """Table 5: where the report located a miss (``concealed.flagged``), by how each recording
    ended (a right name split by whether it halved the held-out error): runs whose baseline's fit to all frames flags a channel, whose baseline's predictions
    of the held-out parts do, and whose final model's predictions still do (runs made before the
    predictions were located are left out of the last two columns and counted apart)."""
    groups: dict[str, list[dict]] = {"named right, held-out error halved": [],
                                     "named right, not halved": [], "effect not named right": [], "control": []}
    for rows in by_set.values():
        for r in rows.values():
            group = ("control" if not r["truth"] else "effect not named right" if not r["right"]
                     else "named right, held-out error halved" if halved(r) else "named right, not halved")
            groups[group].append(r["flagged"])
    lines = ["| recordings | runs | baseline's fit flags a channel | baseline's predictions flag one | "
             "final model's predictions flag one | runs without the predictions' line |", "|---|---|---|---|---|---|"]
    for label, marks in groups.items():
        seen = [m for m in marks if m["predicted"] is not None]
        lines.append(f"| {label} | {len(marks)} | {sum(m['fit'] for m in marks)} | "
                     f"{sum(m['predicted'] for m in seen)} of {len(seen)} | "
                     f"{sum(m['predicted_after'] for m in seen)} of {len(seen)} | {len(marks) - len(seen)} |")
    return "\n".join(lines)


def beside(by_set: dict, other: dict, labels: tuple[str, str]) -> str:
    """Table 6, two variants of the same sets side by side (``by_set`` and ``other``, as
    :func:`runs` gives them; ``labels`` their names): per set the right names (a control's quiet)
    of each, then every recording whose outcome differs, and over every scalar case both ran the
    factor by which the second's detection limit is below the first's (its truth over limit
    over the first's, :func:`concealed.limit_ratio`)."""
    lines = [f"| set | effect cases | right: {labels[0]} | right: {labels[1]} | controls quiet: {labels[0]} | "
             f"controls quiet: {labels[1]} | recordings whose outcome differs ({labels[0]} → {labels[1]}) |",
             "|---|---|---|---|---|---|---|"]
    totals, factors = [0] * 5, []
    for label, rows in by_set.items():
        pairs = [(rows[n], other[label][n]) for n in rows if n in other.get(label, {})]
        effect = [(a, b) for a, b in pairs if a["truth"]]
        control = [(a, b) for a, b in pairs if not a["truth"]]
        counts = [len(effect), sum(a["right"] for a, _ in effect), sum(b["right"] for _, b in effect),
                  sum(a["right"] for a, _ in control), sum(b["right"] for _, b in control)]
        totals = [t + c for t, c in zip(totals, counts)]
        moved = [f"{a['recording']} {grid_word(a)} → {grid_word(b)}" for a, b in pairs if grid_word(a) != grid_word(b)]
        lines.append(f"| {label} | {counts[0]} | {counts[1]} | {counts[2]} | {counts[3]} of {len(control)} | "
                     f"{counts[4]} of {len(control)} | {'; '.join(moved) or 'none'} |")
        for a, b in effect:
            ra, rb = limit_ratio(a), limit_ratio(b)
            if ra and rb and math.isfinite(ra) and math.isfinite(rb):
                factors.append(rb / ra)
    lines.append(f"| **all** | {totals[0]} | {totals[1]} | {totals[2]} | {totals[3]} | {totals[4]} | |")
    if factors:
        median, low, high = statistics.median(factors), min(factors), max(factors)
        lines.append(f"\nOn {len(factors)} scalar cases both ran, {labels[1]}'s detection limit is "
                     + (f"{median:.2f} times lower than {labels[0]}'s (median; {low:.2f}–{high:.2f})." if median >= 1
                        else f"{1 / median:.2f} times higher than {labels[0]}'s (median; {1 / high:.2f}–{1 / low:.2f})."))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("suffix", nargs="?", default=DEFAULT_SUFFIX,
                    help=f"results folder suffix (default {DEFAULT_SUFFIX}, the default path; '' the masks)")
    ap.add_argument("--fresh", type=int, nargs="+", metavar="K", help="these sets instead of the seven (0 the first)")
    ap.add_argument("--each", action="store_true", help="list every scalar case's truth over its limit")
    ap.add_argument("--beside", metavar="OTHER", help="another suffix's runs of the same sets side by side "
                    "with these (a last table; e.g. the default beside its camera of twice the pixels, _x2)")
    args = ap.parse_args(argv)
    sets = tuple(args.fresh) if args.fresh is not None else SEVEN
    by_set = runs(args.suffix, sets)
    print(targets(by_set), outcomes(runs=by_set), verdict_grid(runs=by_set), limits_table(by_set, args.each),
          located_table(by_set), exposure_line(by_set) + " " + outlier_line(by_set), sep="\n\n")
    if args.beside is not None:
        print("\n" + beside(by_set, runs(args.beside, sets), (args.suffix or "''", args.beside)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
