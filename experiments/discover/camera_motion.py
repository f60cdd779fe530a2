"""How far the background of each concealed recording moves (``torchfit.video.camera_motion``).

    python experiments/discover/camera_motion.py SET... [--out FILE]

For every recording in each ``SET`` (folders beside this file, e.g. ``recordings``
``recordings_fresh1``, or any path holding recording folders): the largest and the RMS offset of
its frames' backgrounds, in px, and where the folder holds ``shake.json`` (``shake.py``) the RMS
and largest error of the offsets against the shake's own (both about their medians). The
concealed recordings are filmed from a still camera: their largest offset is what
``SegmentationSettings.stabilise="auto"`` must stay under (:data:`torchfit.video.STILL_PX`) to
leave them as they were. Writes ``results/camera_motion.json`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from torchfit.video import STILL_PX, _read_video, camera_motion

HERE = Path(__file__).resolve().parent


def measure(folder: Path) -> dict:
    """The recording ``folder``'s offsets, summarised (and against its shake when it has one)."""
    frames, _ = _read_video(folder / "video.mp4", 0, None)
    offsets = camera_motion(frames)
    size = np.linalg.norm(offsets, axis=1)
    row = {"largest_px": float(size.max()), "rms_px": float(np.sqrt((size ** 2).mean()))}
    if (folder / "shake.json").exists():
        truth = np.array(json.loads((folder / "shake.json").read_text())["offsets_px"])
        error = (offsets - np.median(offsets - truth, axis=0)) - truth
        row["shake_rms_px"] = float(np.sqrt((truth ** 2).sum(1).mean()))
        row["error_rms_px"] = float(np.sqrt((error ** 2).sum(1).mean()))
        row["error_largest_px"] = float(np.linalg.norm(error, axis=1).max())
    return row


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sets", nargs="+", help="folders of recordings (beside this file or paths)")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "camera_motion.json")
    args = ap.parse_args(argv)
    result = json.loads(args.out.read_text()) if args.out.exists() else {}
    for name in args.sets:
        folder = Path(name) if Path(name).is_absolute() else HERE / name
        for recording in sorted(f for f in folder.iterdir() if (f / "video.mp4").exists()):
            row = measure(recording)
            result[f"{name}/{recording.name}"] = row
            print(name, recording.name, " ".join(f"{k} {v:.3f}" for k, v in row.items()), flush=True)
        args.out.write_text(json.dumps(result, indent=1))
    still = [r["largest_px"] for r in result.values() if "shake_rms_px" not in r]
    if still:
        print(f"{len(still)} without a shake: largest offset {max(still):.3f} px (median {np.median(still):.3f});"
              f" STILL_PX {STILL_PX}")


if __name__ == "__main__":
    main()
