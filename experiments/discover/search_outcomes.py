"""The baseline search alone on every concealed recording: its best loss and how far its pose is from the truth.

    python experiments/discover/search_outcomes.py OUT.jsonl [SET...]   # ~18 s a recording

SET: recording folders under experiments/discover (default: recordings, recordings_fresh1,
recordings_fresh2, recordings_sharp, recordings_fresh2_sharp; make_concealed.py makes them). One
JSON line per recording, appended to OUT.jsonl as it finishes: the best candidate's loss, its
rotation error at t = 0 modulo the shape's symmetries (degrees; meaningless for a ball, whose
orientation the silhouette does not show), its spin and the true spin. To compare two revisions,
run it in a worktree of each (``git worktree add /tmp/old REV``, then
``PYTHONPATH=/tmp/old python experiments/discover/search_outcomes.py old.jsonl``).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch
from true_masks import load_problem, recording_parts

from torchfit.rotation import quat_to_matrix, rotation_angle
from torchfit.search import SearchSettings, fit

HERE = Path(__file__).resolve().parent
SETS = ("recordings", "recordings_fresh1", "recordings_fresh2", "recordings_sharp", "recordings_fresh2_sharp")


def outcome(folder: Path) -> dict:
    """The search's best candidate on ``folder``'s segmented video, against its truth.json."""
    truth, shape, camera = recording_parts(folder)
    _, problem, _ = load_problem(folder, shape, camera, False)
    clock = time.perf_counter()
    result = fit(problem, SearchSettings())
    rot = quat_to_matrix(result.candidates.quat()[:1].double())[0]
    error = rotation_angle(rot @ torch.as_tensor(shape.symmetries, dtype=torch.float64),
                           torch.tensor(truth["params"]["R"], dtype=torch.float64))  # (K,) per symmetry
    return {"recording": f"{folder.parent.name}/{folder.name}", "loss": float(result.losses[0]),
            "rotation_error_deg": float(torch.rad2deg(error).min()),
            "spin": result.candidates.omega[0].tolist(), "true_spin": truth["params"]["angular_velocity"],
            "seconds": time.perf_counter() - clock}


def main(out: Path, sets: list[str]) -> None:
    folders = sorted(p for name in sets for p in (HERE / name).iterdir() if (p / "truth.json").exists())
    if not folders:
        sys.exit(f"no recordings in {', '.join(sets)}: run make_concealed.py first")
    with out.open("a") as stream:
        for folder in folders:
            row = outcome(folder)
            print(json.dumps(row), file=stream, flush=True)
            print(f"{row['recording']}: loss {row['loss']:.5f}, rotation {row['rotation_error_deg']:.1f}°", flush=True)


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(Path(sys.argv[1]), sys.argv[2:] or list(SETS))
