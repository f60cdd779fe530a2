"""The named coefficients against the engine's: how far off, and whether their standard errors say so.

For every concealed run whose verdict is exactly its hidden effect, each hidden scalar parameter's
fitted value against the truth: the ratio fit / truth, and z = (fit - truth) / std (the fit's
reported standard error). Per parameter: the count, the ratio's median and range, z's mean (a
bias in standard errors) and RMS (about 1 when the standard errors are right). From the stored
discover.json files (no fitting).

    python experiments/discover/coefficients.py SUFFIX [--fresh K ...] [--each]

``SUFFIX`` picks the results folders ``results/concealed<set><SUFFIX>`` ('' for the default path,
``_albedo1_exposure_fitted_heldout6`` for the exposure path's complete runs); the six sets unless
``--fresh`` names others (0 the first); ``--each`` lists every recording.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
SIX = (0, 1, 2, 3, 4, 5)


def coefficient_rows(content: dict) -> list[tuple[str, str, float, float, float]]:
    """``(effect, parameter, truth, fitted, std)`` of a run's hidden scalar parameters when its
    verdict is exactly the hidden effects (none otherwise, and none for a parameter whose truth is
    0, a vector, or not fitted)."""
    truth = content.get("truth_effects") or {}
    if not truth or sorted(content["verdict"]) != sorted(truth):
        return []
    fitted = content["models"][-1]["params"]
    rows = []
    for effect, params in truth.items():
        for name, value in params.items():
            got = fitted.get(effect, {}).get(name)
            if got is None or isinstance(value, list) or isinstance(got["value"], list) or value == 0:
                continue
            rows.append((effect, name, float(value), float(got["value"]), float(got["std"])))
    return rows


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
    ap.add_argument("suffix", help="results folder suffix ('' for the default path)")
    ap.add_argument("--fresh", type=int, nargs="+", metavar="K", help="these sets instead of the six (0 the first)")
    ap.add_argument("--each", action="store_true", help="list every recording's ratio and z")
    args = ap.parse_args(argv)
    rows = []
    for k in args.fresh if args.fresh is not None else SIX:
        folder = HERE / "results" / f"concealed{f'_fresh{k}' if k else ''}{args.suffix}"
        if not folder.is_dir():
            raise SystemExit(f"no results folder {folder} (run concealed.py for that set and suffix first)")
        for path in sorted(folder.glob("*/discover.json")):
            for effect, name, truth, fit, std in coefficient_rows(json.loads(path.read_text())):
                rows.append((effect, name, truth, fit, std))
                if args.each:
                    print(f"{folder.name:48s} {path.parent.name:16s} {effect}.{name} {fit:.4g} (true {truth:.4g}) "
                          f"ratio {fit / truth:.3f} z {(fit - truth) / std:+.2f}")
    print("| parameter | named right | fit / truth, median (range) | mean z | RMS z |\n|---|---|---|---|---|")
    for key, s in summary(rows).items():
        print(f"| {key} | {s['n']} | {s['ratio_median']:.3f} ({s['ratio_min']:.2f}–{s['ratio_max']:.2f}) "
              f"| {s['z_mean']:+.2f} | {s['z_rms']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
