"""The search's fit against the truth, before and after discover's exact-moment refinement.

    python experiments/discover/polish_check.py SET:NAME:MASKS...   # ~25 s each
    # SET: ship (torchfit/recordings) or 0, 1, 2 (the concealed sets); MASKS: seg or true

For each recording: the search from no guess (`torchfit.search.fit`, its pixel polish at crop 64,
edge 0.5 crop px), then discover's baseline refinement from that same search result
(Levenberg-Marquardt on the exact silhouette moments with the edge nuisance,
``VideoProblem.fit((), None, searched=...)``, noise floor's edge term ``EDGE_PX`` on the
segmentation and ``concealed.EXACT_EDGE_PX`` on true masks). Printed: each
one's error at the first fitted frame (:func:`torchfit.report.score_against_truth`): rotation
(degrees, modulo the shape's symmetries), position (mm) and its lateral part (mm), gravity
direction (degrees).
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import torch
from concealed import EXACT_EDGE_PX
from make_concealed import fresh_folder
from true_masks import load_problem, recording_parts

from torchfit.discover_video import EDGE_PX, VideoProblem
from torchfit.report import score_against_truth
from torchfit.search import SearchSettings, fit

SHIPPED = Path(__file__).resolve().parents[2] / "torchfit" / "recordings"


def errors(folder: Path, state: torch.Tensor, cands, problem, shape, span) -> str:
    """One line of a (1, 13) state's errors against ``folder``'s truth.json (``cands``: its
    :class:`torchfit.search.Candidates`, for the gravity)."""
    score = score_against_truth(str(folder / "truth.json"), SimpleNamespace(state=state, candidates=cands,
                                losses=torch.zeros(1)), problem, shape, span)
    truth = recording_parts(folder)[0]["per_frame"]["position"][int(span[0])]
    lateral = 1000 * math.dist(state[0, :2].double().tolist(), truth[:2])
    return (f"rot={score['rotation_error_deg']:.3f} pos_mm={1000 * score['position_error_m']:.3f} "
            f"lat_mm={lateral:.3f} grav={score['gravity_error_deg']:.3f}")


def main(args: list[str]) -> None:
    for arg in args:
        which, name, kind = arg.split(":")
        folder = (SHIPPED if which == "ship" else fresh_folder(int(which))) / name
        _, shape, camera = recording_parts(folder)
        _, problem, span = load_problem(folder, shape, camera, kind == "true")
        clock = time.perf_counter()
        result = fit(problem, SearchSettings(), progress=None)
        video = VideoProblem(problem, candidates=(), edge_px=EDGE_PX if kind == "seg" else EXACT_EDGE_PX)
        model = video.fit((), None, searched=result).payload["model"]
        refined = model.cands.state(video.problem.body)
        print(f"{arg} search {errors(folder, result.state[:1], result.candidates, problem, shape, span)} | "
              f"LM {errors(folder, refined, model.cands, problem, shape, span)} edge {model.nuisances[0]:+.3f} "
              f"({time.perf_counter() - clock:.0f} s)", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
