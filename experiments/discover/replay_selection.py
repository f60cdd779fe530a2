"""Replay discover's forward selection from stored scores, tests left out or decided otherwise.

Every candidate's scores of every round a run reached are stored (``effects[name][round]``, with
the tests it failed); forward selection (:func:`torchfit.discover.select_effects`) names each
round's strongest passing candidate, or reports look-alikes within ``lookalike_margin``. Replaying
it with some tests ignored says which verdicts those tests decided, exactly while the replay adds
the names the stored run added: where it adds another (or one more), the stored run never scored
the next round, and the row says a rerun is needed.

Prints the recordings whose verdict the replay changes, then per set the verdicts as run and as
replayed: right names (the hidden effect named alone), controls quiet, runs with a name that is
not hidden.

    python experiments/discover/replay_selection.py SUFFIX --drop heldout
    python experiments/discover/replay_selection.py SUFFIX --heldout-rule rms
    python experiments/discover/replay_selection.py SUFFIX --heldout-rule rms --against OTHER
    python experiments/discover/replay_selection.py SUFFIX --min-delta-bic 0

``--against OTHER`` also lists, recording by recording, where the replayed verdicts of two
variants' runs (``SUFFIX`` and ``OTHER``) differ, or where either needs a rerun.

``SUFFIX`` picks the results folders ``results/concealed<set><SUFFIX>`` of the six sets ('' for
the default path, ``_albedo1_exposure_fitted`` for the exposure path); ``--fresh K [K ...]``
other sets instead (0 the first).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

from torchfit.discover import SelectionSettings, bar_failures
from torchfit.discover_video import VIDEO_SELECTION

HERE = Path(__file__).resolve().parent
SETS = ("", "_fresh1", "_fresh2", "_fresh3", "_fresh4", "_fresh5")
TESTS = ("delta_bic", "unphysical", "evidence_spread", "heldout", "wald")


def rms_rule(score: dict, rules: SelectionSettings = VIDEO_SELECTION) -> bool:
    """Whether a candidate passes the held-out RMS rule (``min_heldout_gain``, ``heldout_noise``)."""
    return score["heldout_gain"] >= rules.min_heldout_gain or (
        rules.heldout_noise is not None and score["heldout_rms_after"] <= rules.heldout_noise)


def deviance_rule(margin: float) -> Callable[[dict], bool]:
    """The held-out deviance rule with this margin (runs that stored the deviance)."""
    return lambda score: score["heldout_deviance_rise"] <= margin


def replay(content: dict, drop: tuple[str, ...] = (), heldout: Callable[[dict], bool] | None = None,
           margin: float = VIDEO_SELECTION.lookalike_margin, max_effects: int = 3,
           min_delta_bic: float | None = None) -> tuple[list[str], list[str] | None, bool]:
    """(names, look-alikes or None, exact) of forward selection on a run's stored scores with
    the tests in ``drop`` ignored and, when ``heldout`` is given, the held-out test decided by it
    (score -> passes), and, when ``min_delta_bic`` is given, the ΔBIC and Wald tests decided
    against that bar instead of the run's (``SelectionSettings.min_delta_bic``); ``exact`` is False
    where the stored run did not score the round the replay reached (the last name is then the
    replay's, unconfirmed)."""

    def fails(score: dict) -> set[str]:
        out = set(score["fails"]) - set(drop)
        if min_delta_bic is not None:  # the bar's two tests decided again, by select_effects' rule
            bar = bar_failures(score["delta_bic"], score.get("wald_delta_bic"), min_delta_bic)
            out = (out - set(bar)) | {test for test, failed in bar.items() if failed and test not in drop}
        if heldout is not None and "heldout" not in drop:
            out = (out - {"heldout"}) | (set() if heldout(score) else {"heldout"})
        return out

    scores, chain = content["effects"], content.get("verdict_withheld") or content["verdict"]
    names: list[str] = []
    while len(names) < max_effects:
        rnd = len(names)
        step = {n: rounds[rnd] for n, rounds in scores.items() if n not in names and rnd < len(rounds)}
        passing = sorted((s["delta_bic"], n) for n, s in step.items() if not fails(s))
        if not passing:
            return names, None, True
        best, winner = passing[-1]
        alike = [n for d, n in passing[:-1] if best - d < margin]
        if alike:
            return names, [winner, *alike], True
        if rnd >= len(chain) or chain[rnd] != winner:
            return names + [winner], None, False
        names.append(winner)
    return names, None, True


def reported(content: dict, names: list[str]) -> list[str]:
    """The verdict a replay that names ``names`` reports: the stored verdict as reported ([] where
    it was withheld for a poor fit) while those are the stored names, else ``names``."""
    return content["verdict"] if names == (content.get("verdict_withheld") or content["verdict"]) else names


def replayed(content: dict, drop: tuple[str, ...] = (), heldout: Callable[[dict], bool] | None = None,
             min_delta_bic: float | None = None) -> tuple[list[str], list[str] | None, bool]:
    """:func:`replay`'s names as reported (:func:`reported`), its look-alikes and whether it is exact."""
    names, alike, exact = replay(content, drop, heldout, min_delta_bic=min_delta_bic)
    return reported(content, names), alike, exact


def _said(verdict: tuple[list[str], list[str] | None, bool]) -> str:
    """A replayed verdict (:func:`replayed`) in words."""
    return (f"{verdict[0]}" + (f" (look-alikes {verdict[1]})" if verdict[1] else "")
            + ("" if verdict[2] else " (needs a rerun)"))


def differences(first: Path, second: Path, drop: tuple[str, ...] = (),
                heldout: Callable[[dict], bool] | None = None, min_delta_bic: float | None = None) -> list[str]:
    """One line per recording run in both results folders whose replayed verdicts
    (:func:`replayed`) differ, or where either replay needs a rerun."""
    lines = []
    for path in sorted(first.glob("*/discover.json")):
        other = second / path.parent.name / "discover.json"
        if not other.exists():
            continue
        content = json.loads(path.read_text())
        a, b = (replayed(run, drop, heldout, min_delta_bic) for run in (content, json.loads(other.read_text())))
        if a != b or not (a[2] and b[2]):
            lines.append(f"{path.parent.name:16s} hidden {sorted(content['truth_effects'] or {})}: "
                         f"{_said(a)} against {_said(b)}")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("suffix", help="results folder suffix ('' for the default path)")
    ap.add_argument("--drop", default="", help=f"tests to ignore, comma-separated, among {TESTS}")
    ap.add_argument("--heldout-rule", choices=("rms", "deviance"),
                    help="decide the held-out test by the RMS rule (VIDEO_SELECTION's) or by the predictive "
                         "deviance within --margin (runs that stored it)")
    ap.add_argument("--margin", type=float, default=6.0, help="the deviance rule's margin (default 6)")
    ap.add_argument("--min-delta-bic", type=float, metavar="BAR",
                    help="decide the ΔBIC and Wald tests against this bar instead of the runs' "
                         f"({VIDEO_SELECTION.min_delta_bic:g}): a candidate must lower the BIC by more than BAR")
    ap.add_argument("--fresh", type=int, nargs="+", metavar="K",
                    help="fresh sets K instead of the six (e.g. --fresh 6: a set no rule has seen, counted apart)")
    ap.add_argument("--against", metavar="OTHER",
                    help="also list the recordings whose replayed verdict differs from the runs of suffix OTHER")
    args = ap.parse_args(argv)
    sets = SETS if args.fresh is None else tuple(f"_fresh{k}" if k else "" for k in args.fresh)
    heldout = {"rms": rms_rule, "deviance": deviance_rule(args.margin), None: None}[args.heldout_rule]
    drop = tuple(t for t in args.drop.split(",") if t)
    if set(drop) - set(TESTS):
        ap.error(f"--drop: unknown tests {sorted(set(drop) - set(TESTS))}; choose among {TESTS}")
    tally = {}  # set -> {"stored" | "replay": [right effects, effect cases, controls quiet, controls, wrong]}
    unsettled = 0
    for fresh in sets:
        folder = HERE / "results" / f"concealed{fresh}{args.suffix}"
        for path in sorted(folder.glob("*/discover.json")):
            content = json.loads(path.read_text())
            truth = sorted(content["truth_effects"] or {})
            stored = content.get("verdict_withheld") or content["verdict"]
            names, alike, exact = replay(content)
            if not exact or names != stored:  # the replay must reproduce the stored selection
                raise SystemExit(f"{path}: the replay without changes gives {names}, stored {stored}")
            names, alike, exact = replay(content, drop, heldout, min_delta_bic=args.min_delta_bic)
            if names != stored or not exact or (alike and not content["indistinguishable"]):
                print(f"{fresh or 'first':8s} {path.parent.name:16s} hidden {truth}: stored {stored}, replay {names}"
                      + (f" (look-alikes {alike})" if alike else "") + ("" if exact else " — needs a rerun"))
            label = fresh.replace("_fresh", "fresh ") or "first"
            counts = tally.setdefault(label, {"stored": [0] * 5, "replay": [0] * 5})
            # the stored verdict as reported ([] where withheld for a poor fit); the replay keeps the
            # withholding where its names are the stored ones
            for key, named, ties, settled in (("stored", content["verdict"], content["indistinguishable"], True),
                                              ("replay", reported(content, names), alike, exact)):
                if not settled:
                    unsettled += key == "replay"
                    continue
                row = counts[key]
                if truth:
                    row[0] += sorted(named) == truth and not ties
                    row[1] += 1
                else:
                    row[2] += not (named or ties)
                    row[3] += 1
                row[4] += bool(set(named) - set(truth))
    lines = ["| set | verdicts | right | controls quiet | runs with a wrong name |", "|---|---|---|---|---|"]
    total = {"stored": [0] * 5, "replay": [0] * 5}
    for name, counts in [*tally.items(), ("**all**", total)]:
        for key in ("stored", "replay"):
            row = counts[key]
            if name != "**all**":
                total[key] = [a + b for a, b in zip(total[key], row)]
            label = "as run" if key == "stored" else "replayed"
            lines.append(f"| {name} | {label} | {row[0]} of {row[1]} | {row[2]} of {row[3]} | {row[4]} |")
    print("\n".join(lines))
    print(f"{unsettled} replayed runs need a rerun (left out of the replay's counts)")
    if args.against is not None:
        print(f"\nWhere {args.suffix or 'the default'} and {args.against or 'the default'} differ, replayed:")
        for fresh in sets:
            for line in differences(HERE / "results" / f"concealed{fresh}{args.suffix}",
                                    HERE / "results" / f"concealed{fresh}{args.against}", drop, heldout,
                                    args.min_delta_bic):
                print(f"{fresh or 'first':8s} {line}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
