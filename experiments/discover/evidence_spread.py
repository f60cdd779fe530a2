"""Where each candidate's evidence lies, from the per-frame chi-squared change discover stores.

    python experiments/discover/evidence_spread.py [concealed concealed_true_masks concealed_fresh1 ... shipped]

For every scored candidate of every discover.json under results/<set>/ that stores
``unit_delta_chi2``: its ΔBIC, and its ΔBIC with the weakest of 3, 4 or 5 contiguous stretches of
the frames left out (``without_weakest_block``, the rule's statistic at 3) or without its 3 or 5
strongest frames. Prints the candidates that lowered the BIC by more than the threshold, or that
are the hidden effect, and writes everything to results/evidence_spread.json: how the rule's
choice (thirds, ΔBIC > 0) compares with its alternatives on the same fits.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from torchfit.discover import without_weakest_block

RESULTS = Path(__file__).resolve().parent / "results"


def statistics(score: dict) -> dict:
    """ΔBIC without the weakest third, quarter, fifth, and without the 3 and 5 strongest frames."""
    parts, d_bic = np.asarray(score["unit_delta_chi2"]), score["delta_bic"]
    out = {f"without_weakest_of_{b}": without_weakest_block(parts, d_bic, b)[0] for b in (3, 4, 5)}
    strongest = np.sort(parts)[::-1]
    out.update({f"without_strongest_{m}": d_bic - float(strongest[:m].sum()) for m in (3, 5)})
    return out


def main(sets: list[str]) -> None:
    rows = []
    for name in sets:
        for path in sorted((RESULTS / name).glob("*/discover.json")):
            content = json.loads(path.read_text())
            hidden = set(content.get("truth_effects", {}))
            threshold = content["settings"]["min_delta_bic"]
            for effect, scores in content["effects"].items():
                for score in scores:
                    if "unit_delta_chi2" not in score:
                        continue
                    rows.append({"set": name, "recording": path.parent.name, "base": score["base"],
                                 "candidate": effect, "hidden": effect in hidden, "passes": score["passes"],
                                 "delta_bic": score["delta_bic"], **statistics(score)})
                    row = rows[-1]
                    if row["delta_bic"] > threshold or row["hidden"]:
                        print(f"{name:21s} {row['recording']:16s} {'+'.join(row['base']) or 'baseline':15s} "
                              f"{effect:16s} {'hidden' if row['hidden'] else '      '} passes={int(row['passes'])} "
                              f"ΔBIC {row['delta_bic']:7.1f} | without weakest third/quarter/fifth "
                              f"{row['without_weakest_of_3']:6.1f} {row['without_weakest_of_4']:6.1f} "
                              f"{row['without_weakest_of_5']:6.1f} | without strongest 3/5 frames "
                              f"{row['without_strongest_3']:6.1f} {row['without_strongest_5']:6.1f}")
    (RESULTS / "evidence_spread.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main(sys.argv[1:] or ["concealed", "concealed_true_masks", "concealed_fresh1", "concealed_fresh1_true_masks",
                          "shipped"])
