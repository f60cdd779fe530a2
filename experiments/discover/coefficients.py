"""The named coefficients against the engine's: how far off, and whether their standard errors say so.

For every concealed run whose verdict is exactly its hidden effect, each hidden scalar parameter's
fitted value against the truth: the ratio fit / truth, and z = (fit - truth) / std (the fit's
reported standard error). Per parameter: the count, the ratio's median and range, z's mean (a
bias in standard errors) and RMS (about 1 when the standard errors are right). From the stored
discover.json files (no fitting).

``--unselected`` asks the same of every run, named or not, so no threshold picks the rows: each
hidden scalar parameter from the first round's fit of the baseline plus the hidden effect alone
(``effects[hidden][0]``), against the truth; and on the controls, each candidate's first-round
Wald statistic and chi-squared drop against its degrees of freedom (means about the degrees of
freedom when the noise floors are right in that candidate's direction).

    python experiments/discover/coefficients.py SUFFIX [--fresh K ...] [--each] [--unselected]

``SUFFIX`` picks the results folders ``results/concealed<set><SUFFIX>``
(``_albedo1_exposure0.5_taps0_fitted_huber2_backcast_final12`` for the default path, '' for the masks); the
six sets unless ``--fresh`` names others (0 the first); ``--each`` lists every recording.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # concealed.py imports true_masks from its folder
SIX = (0, 1, 2, 3, 4, 5)

from concealed import ball_lift, lens_shift_against_truth, spin_hidden  # noqa: E402


def _scalar_rows(truth: dict, fitted_of) -> list[tuple[str, str, float, float, float]]:
    """``(effect, parameter, truth, fitted, std)`` of each hidden scalar parameter in ``truth``
    (``{effect: {parameter: value}}``) that ``fitted_of(effect)`` (``{parameter: {"value", "std"}}``)
    holds; none for a parameter whose truth is 0, a vector, or not fitted."""
    rows = []
    for effect, params in truth.items():
        fitted = fitted_of(effect)
        for name, value in params.items():
            got = fitted.get(name)
            if got is None or isinstance(value, list) or isinstance(got["value"], list) or value == 0:
                continue
            rows.append((effect, name, float(value), float(got["value"]), float(got["std"])))
    return rows


def coefficient_rows(content: dict) -> list[tuple[str, str, float, float, float]]:
    """``(effect, parameter, truth, fitted, std)`` of a run's hidden scalar parameters when its
    verdict is exactly the hidden effects (none otherwise, and none for a parameter whose truth is
    0, a vector, or not fitted)."""
    truth = content.get("truth_effects") or {}
    if not truth or sorted(content["verdict"]) != sorted(truth):
        return []
    fitted = content["models"][-1]["params"]
    rows = _scalar_rows(truth, lambda effect: fitted.get(effect, {}))
    shift = lens_shift_against_truth(content)
    if shift is not None:  # k1 and k2 trade: the lens's shift where the object went farthest
        rows.append(("lens_distortion", "shift_px", shift["true"], shift["fitted"], shift["std"]))
    lift = ball_lift(content)
    if lift is None:
        return rows
    # a ball's C_L trades with its unseen spin: its lift is the vector C_L ω's part across the
    # direction the video sees least (concealed.ball_lift)
    return [r for r in rows if r[:2] != ("magnus", "lift_coefficient")] + \
        [("magnus", "lift_across", lift["true"], lift["fitted"], lift["std"])]


def unselected_rows(content: dict) -> list[tuple[str, str, float, float, float]]:
    """``(effect, parameter, truth, fitted, std)`` of a run's hidden scalar parameters from the
    first round's fit of the hidden effect alone, whatever the verdict (none for a control, a
    vector, a truth of 0, or a run that did not score the effect; none for a ball's lift, whose
    C_L trades with its unseen spin)."""
    effects = content.get("effects", {})
    truth = {e: p for e, p in (content.get("truth_effects") or {}).items()
             if effects.get(e) and not (spin_hidden(content) and e == "magnus")}
    return _scalar_rows(truth, lambda effect: effects[effect][0]["params"].get(effect, {}))


def control_rows(content: dict) -> list[tuple[str, int, float, float]]:
    """``(candidate, degrees of freedom, Wald statistic, chi-squared drop)`` of each first-round
    candidate of a control (a run with no hidden effect; none otherwise)."""
    if content.get("truth_effects"):
        return []
    return [(name, int(rounds[0]["delta_dof"]), float(rounds[0]["wald_chi2"]), float(rounds[0]["delta_chi2"]))
            for name, rounds in content.get("effects", {}).items() if rounds and "wald_chi2" in rounds[0]]


def summary(rows: list[tuple[str, str, float, float, float]]) -> dict:
    """``{"effect.parameter": {"n", "ratio_median", "ratio_min", "ratio_max", "z_mean", "z_rms"}}``."""
    out: dict = {}
    by: dict = {}
    for effect, name, truth, fit, std in rows:
        by.setdefault(f"{effect}.{name}", []).append((fit / truth, (fit - truth) / std))
    for key, pairs in by.items():
        ratios, zs = [r for r, _ in pairs], [z for _, z in pairs]
        out[key] = {"n": len(pairs), "ratio_median": statistics.median(ratios), "ratio_min": min(ratios),
                    "ratio_max": max(ratios), "z_mean": statistics.fmean(zs),
                    "z_rms": math.sqrt(statistics.fmean([z * z for z in zs]))}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("suffix", help="results folder suffix (_albedo1_exposure0.5_taps0_fitted_huber2_backcast_final12 for the default "
                                   "path, '' for the masks)")
    ap.add_argument("--fresh", type=int, nargs="+", metavar="K", help="these sets instead of the six (0 the first)")
    ap.add_argument("--each", action="store_true", help="list every recording's ratio and z")
    ap.add_argument("--unselected", action="store_true",
                    help="every run's first-round fit of its hidden effect, named or not, and the controls' "
                         "first-round candidates")
    args = ap.parse_args(argv)
    read = unselected_rows if args.unselected else coefficient_rows
    rows, controls = [], []
    for k in args.fresh if args.fresh is not None else SIX:
        folder = HERE / "results" / f"concealed{f'_fresh{k}' if k else ''}{args.suffix}"
        if not folder.is_dir():
            raise SystemExit(f"no results folder {folder} (run concealed.py for that set and suffix first)")
        for path in sorted(folder.glob("*/discover.json")):
            content = json.loads(path.read_text())
            controls += control_rows(content) if args.unselected else []
            for effect, name, truth, fit, std in read(content):
                rows.append((effect, name, truth, fit, std))
                if args.each:
                    print(f"{folder.name:48s} {path.parent.name:16s} {effect}.{name} {fit:.4g} (true {truth:.4g}) "
                          f"ratio {fit / truth:.3f} z {(fit - truth) / std:+.2f}")
    print(f"| parameter | {'every run, first round' if args.unselected else 'named right'} | fit / truth, median (range) | mean z | RMS z |\n|---|---|---|---|---|")
    for key, s in summary(rows).items():
        print(f"| {key} | {s['n']} | {s['ratio_median']:.3f} ({s['ratio_min']:.2f}–{s['ratio_max']:.2f}) "
              f"| {s['z_mean']:+.2f} | {s['z_rms']:.2f} |")
    if args.unselected:
        print("\n| control candidate | runs | degrees of freedom | mean Wald | mean chi-squared drop |\n|---|---|---|---|---|")
        for name in dict.fromkeys(c[0] for c in controls):
            mine = [c for c in controls if c[0] == name]
            dofs = sorted({c[1] for c in mine})
            print(f"| {name} | {len(mine)} | {'/'.join(map(str, dofs))} | {statistics.fmean(c[2] for c in mine):.2f} "
                  f"| {statistics.fmean(c[3] for c in mine):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
