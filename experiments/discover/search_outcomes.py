"""The baseline search alone on every concealed recording: its best loss and how far its pose is from the truth.

    python experiments/discover/search_outcomes.py OUT.jsonl [SET...]   # ~18 s a recording
    python experiments/discover/search_outcomes.py OUT.jsonl --final 6,12 --albedo-passes 1 --no-balls [SET...]
    python experiments/discover/search_outcomes.py OUT.jsonl --summary   # the two settings side by side

SET: recording folders under experiments/discover (default: recordings, recordings_fresh1,
recordings_fresh2, recordings_sharp, recordings_fresh2_sharp; make_concealed.py makes them). One
JSON line per recording, appended to OUT.jsonl as it finishes: for each ``SearchSettings.final``
asked for (``--final A,B``: both, one after the other in this process, alternating which goes
first from one recording to the next; default ``SearchSettings``' own), the best candidate's loss
on the polish's objective, its rotation error at t = 0 modulo the shape's symmetries (degrees;
meaningless for a ball, whose orientation the silhouette does not show, so ``--no-balls`` leaves
them out), its spin, and the search's seconds; and the true spin. ``--albedo-passes N``: segment
with ``SegmentationSettings.albedo_passes`` N (1 is what discover does by default; 0, the
segmentation's own default, when not given). ``--only a,b``: those recordings of each set.
``--summary`` reads OUT.jsonl written with two finals and prints how the second compares with
the first. To compare two revisions, run it in a
worktree of each (``git worktree add /tmp/old REV``, then ``PYTHONPATH=/tmp/old python
experiments/discover/search_outcomes.py old.jsonl``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch
from true_masks import load_problem, recording_parts

from torchfit.rotation import quat_to_matrix, rotation_angle
from torchfit.search import SearchSettings, fit
from torchfit.video import SegmentationSettings

HERE = Path(__file__).resolve().parent
SETS = ("recordings", "recordings_fresh1", "recordings_fresh2", "recordings_sharp", "recordings_fresh2_sharp")
LOST_DEG = 5.0  # a best candidate farther than this from the true orientation is counted as off


def outcome(folder: Path, finals: list[int], albedo_passes: int | None = None, first: int = 0) -> dict:
    """The search's best candidate on ``folder``'s segmented video with each of ``finals``
    (``SearchSettings.final``), run in turn starting from ``finals[first]``,
    against its truth.json: ``{"recording", "shape", "true_spin", "finals": [str(final), ...] in
    the order asked for, "runs": {str(final): {"loss", "rotation_error_deg", "spin", "seconds"}}}``."""
    truth, shape, camera = recording_parts(folder)
    settings = None if albedo_passes is None else SegmentationSettings(albedo_passes=albedo_passes)
    _, problem, _ = load_problem(folder, shape, camera, False, settings)
    symmetries = torch.as_tensor(shape.symmetries, dtype=torch.float64)
    true_rot = torch.tensor(truth["params"]["R"], dtype=torch.float64)
    runs = {}
    for final in finals[first:] + finals[:first]:
        clock = time.perf_counter()
        result = fit(problem, SearchSettings(final=final), progress=None)
        seconds = time.perf_counter() - clock
        rot = quat_to_matrix(result.candidates.quat()[:1].double())[0]
        error = rotation_angle(rot @ symmetries, true_rot)  # (K,) per symmetry
        runs[str(final)] = {
            "loss": float(result.losses[0]), "rotation_error_deg": float(torch.rad2deg(error).min()),
            "spin": result.candidates.omega[0].tolist(), "seconds": seconds}
    return {"recording": f"{folder.parent.name}/{folder.name}", "shape": truth["shape"],
            "true_spin": truth["params"]["angular_velocity"], "finals": [str(f) for f in finals], "runs": runs}


def summary(rows: list[dict]) -> str:
    """How the second final of every row compares with the first: losses more than 1 % above and
    below, within 0.001 %, the largest other change, the first's best more than ``LOST_DEG`` off,
    and the seconds' ratio (median and range). ``rows``: OUT.jsonl's lines, each with two runs."""
    keys = rows[0]["finals"]
    if len(keys) != 2 or any(r["finals"] != keys for r in rows):
        raise ValueError(f"--summary needs every line run with the same two finals (--final A,B), "
                         f"got {sorted({tuple(r['finals']) for r in rows})}")
    a, b = keys
    change = {r["recording"]: r["runs"][b]["loss"] / r["runs"][a]["loss"] - 1 for r in rows}
    ratio = [r["runs"][b]["seconds"] / r["runs"][a]["seconds"] for r in rows]
    worse = sorted(n for n, c in change.items() if c > 0.01)
    better = sorted(n for n, c in change.items() if c < -0.01)
    rest = {n: c for n, c in change.items() if abs(c) <= 0.01}
    largest = max(rest, key=lambda n: abs(rest[n])) if rest else None
    off = sorted(r["recording"] for r in rows if r["runs"][a]["rotation_error_deg"] > LOST_DEG)
    lines = [f"{len(rows)} recordings, final={b} against final={a}:",
             f"- more than 1 % above: {len(worse)} {worse}",
             f"- more than 1 % below: {len(better)} " + ", ".join(
                 f"{n} ({100 * change[n]:+.1f} %: {_deg(rows, n, a)} → {_deg(rows, n, b)})" for n in better),
             f"- within 0.001 %: {sum(abs(c) <= 1e-5 for c in change.values())}",
             f"- the largest other change: {largest} ({100 * rest[largest]:+.3f} %)" if largest else "- no other",
             f"- final={a}'s best more than {LOST_DEG:g}° from the truth: {len(off)} {off}",
             f"- seconds, final={b} over final={a}: median {statistics.median(ratio):.2f} "
             f"(range {min(ratio):.2f}–{max(ratio):.2f}); sums {sum(r['runs'][b]['seconds'] for r in rows) / sum(r['runs'][a]['seconds'] for r in rows):.2f}"]
    return "\n".join(lines)


def _deg(rows: list[dict], name: str, final: str) -> str:
    row = next(r for r in rows if r["recording"] == name)
    return f"{row['runs'][final]['rotation_error_deg']:.1f}°"


def _finals(text: str | None) -> list[int]:
    """``--final``'s values; ``SearchSettings``' own when not given."""
    if text is None:
        return [SearchSettings().final]
    try:
        finals = [int(v) for v in text.split(",")]
    except ValueError:
        finals = []
    if not finals or any(v < 1 for v in finals) or len(set(finals)) != len(finals):
        raise SystemExit(f"--final takes distinct whole numbers >= 1 separated by commas, got {text!r}")
    return finals


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="JSON lines, appended to")
    ap.add_argument("sets", nargs="*", default=list(SETS), help="recording folders under experiments/discover")
    ap.add_argument("--final", default=None, metavar="A[,B]", help="SearchSettings.final values, each run in turn")
    ap.add_argument("--albedo-passes", type=int, default=None, metavar="N", help="SegmentationSettings.albedo_passes")
    ap.add_argument("--no-balls", action="store_true", help="leave the balls out (their orientation is not seen)")
    ap.add_argument("--only", action="append", default=[], help="recording names (repeatable / a,b)")
    ap.add_argument("--summary", action="store_true", help="only compare OUT's two finals")
    args = ap.parse_args(argv)
    if args.summary:
        print(summary([json.loads(line) for line in args.out.read_text().splitlines() if line.strip()]))
        return
    finals = _finals(args.final)
    folders = sorted(p for name in args.sets for p in (HERE / name).iterdir() if (p / "truth.json").exists())
    only = {n for item in args.only for n in item.split(",")}
    if only:
        folders = [p for p in folders if p.name in only]
    if args.no_balls:
        folders = [p for p in folders if not _is_ball(p)]
    if not folders:
        sys.exit(f"no recordings in {', '.join(args.sets)}: run make_concealed.py first")
    with args.out.open("a") as stream:
        for i, folder in enumerate(folders):
            row = outcome(folder, finals, args.albedo_passes, first=i % len(finals))
            print(json.dumps(row), file=stream, flush=True)
            print(f"{row['recording']}: " + "; ".join(
                f"final={k} loss {v['loss']:.5f}, rotation {v['rotation_error_deg']:.1f}°, {v['seconds']:.0f} s"
                for k, v in row["runs"].items()), flush=True)


def _is_ball(folder: Path) -> bool:
    return json.loads((folder / "truth.json").read_text())["shape"] == "sphere"


if __name__ == "__main__":
    main()
