"""How far the background of each concealed recording moves (``torchfit.video.camera_motion``).

    python experiments/discover/camera_motion.py SET... [--out FILE] [--min-correlation C]
    python experiments/discover/camera_motion.py --summary [--out FILE] [--sigma-scale S]
    python experiments/discover/camera_motion.py SET... --time-against-passes N [--repeats R]

For every recording in each ``SET`` (folders beside this file, e.g. ``recordings``
``recordings_fresh1``, or any path holding recording folders), registered through its own
``camera.json`` as ``load_observation`` does: the largest move of any pixel of
its frames' backgrounds (a corner), the RMS shift of the image centre, in px, and the RMS turn
about it, in degrees. Where the folder holds ``shake.json`` (``shake.py``): how far from the
shake's own map the found one puts a still frame's corners and centre (RMS over the frames of
the worst corner, the largest, the centre's RMS; each point's error about its median over the
frames), and for a shake of the picture (no ``--turn``) the RMS and largest error of the
centre's shift and the RMS error of the turn (about their medians). Each row also holds every
frame's background correlation with the clip's and whether it registered (``frame_correlation``,
``frame_registered``; ``--min-correlation`` sets the floor, :data:`torchfit.video.MOTION_MIN_CORRELATION`
by default), every frame's worst-corner error against the shake's map, or the identity without
one (``frame_corner_error_px``; each corner's, ``corner_errors_px``), each corner's standard
error (``corner_sigma_px``) and each frame's chi-squared (``frame_chi2``, ``chi2_per_dof``;
``torchfit.video.CameraMotion``). ``--time-against-passes N`` times the registration instead,
OpenCV on one thread (set ``OMP_NUM_THREADS=1`` for numpy's), against itself held to at most ``N`` passes (``max_passes``), the two
alternated ``R`` times per recording in this one process, and prints each recording's median
ratio and their median (the registration before the passes settled ran two). The concealed recordings are filmed from a
still camera: their largest move is what ``SegmentationSettings.stabilise="auto"`` must stay
under (:data:`torchfit.video.STILL_PX`) to leave them as they were. Writes
``results/camera_motion.json`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from shake import shake_maps, shake_motion
from torchfit.camera import Camera
from torchfit.video import (MOTION_MAX_PASSES, MOTION_MIN_CORRELATION, STILL_PX, _corners, _largest_move, _mapped,
                            _motion_rows, _read_video, camera_motion)

HERE = Path(__file__).resolve().parent


def recordings(name: str) -> list[Path]:
    """The recording folders (those holding a video.mp4) of the set ``name``: a folder beside
    this file or a path."""
    folder = Path(name) if Path(name).is_absolute() else HERE / name
    return sorted(f for f in folder.iterdir() if (f / "video.mp4").exists())


def measure(folder: Path, min_correlation: float = MOTION_MIN_CORRELATION) -> dict:
    """The recording ``folder``'s motion, summarised (and against its shake when it has one)."""
    frames, _ = _read_video(folder / "video.mp4", 0, None)
    size = frames.shape[1:3]
    found = camera_motion(frames, Camera.from_file(folder / "camera.json"), min_correlation=min_correlation)
    maps, correlation, registered = found.maps, found.correlation, found.registered
    motion = _motion_rows(maps, size)  # the centre's move and the turn there
    shift = np.linalg.norm(motion[:, :2], axis=1)
    row = {"largest_px": _largest_move(maps, size), "rms_px": float(np.sqrt((shift ** 2).mean())),
           "turn_rms_deg": float(np.sqrt((motion[:, 2] ** 2).mean())),
           "refused": int((~registered).sum()), "correlation_min": float(np.nanmin(correlation, initial=np.inf))}
    shake = json.loads((folder / "shake.json").read_text()) if (folder / "shake.json").exists() else None
    truth_maps = np.tile(np.eye(3), (len(maps), 1, 1)) if shake is None else shake_maps(shake, size)
    # where the image centre and the corners of a still frame lie in each frame, found and true (a
    # still recording's truth: the identity), about their medians over the frames (a registration is
    # relative to the clip's own frames)
    points = np.vstack([_corners(size), [[(size[1] - 1) / 2, (size[0] - 1) / 2, 1.0]]])
    apart = _mapped(maps, points) - _mapped(truth_maps, points)
    apart = np.linalg.norm(apart - np.median(apart, axis=0), axis=2)  # (T, 5)
    row["frame_corner_error_px"] = apart[:, :4].max(1).tolist()
    row["corner_errors_px"] = apart[:, :4].tolist()
    if shake is not None:
        row["shake_rms_px"] = float(np.sqrt((np.asarray(shake["offsets_px"]) ** 2).sum(1).mean()))
        row["corner_error_rms_px"] = float(np.sqrt((apart[:, :4].max(1) ** 2).mean()))
        row["corner_error_largest_px"] = float(apart[:, :4].max())
        row["centre_error_rms_px"] = float(np.sqrt((apart[:, 4] ** 2).mean()))
        if "maps" in shake:  # a turned camera: its pan and tilt
            row["shake_pan_tilt_rms_deg"] = float(np.sqrt((np.asarray(shake["turn_deg"]) ** 2).mean()))
        else:  # a shift and a turn of the picture: the rows themselves
            truth = shake_motion(shake)
            error = motion - np.median(motion - truth, axis=0) - truth
            row["shake_turn_rms_deg"] = float(np.sqrt((truth[:, 2] ** 2).mean()))
            row["error_rms_px"] = float(np.sqrt((error[:, :2] ** 2).sum(1).mean()))
            row["error_largest_px"] = float(np.linalg.norm(error[:, :2], axis=1).max())
            row["turn_error_rms_deg"] = float(np.sqrt((error[:, 2] ** 2).mean()))
    row["frame_correlation"] = [float(c) if np.isfinite(c) else None for c in correlation]
    row["frame_registered"] = registered.tolist()
    row["corner_sigma_px"] = np.where(np.isfinite(found.sigma_px), found.sigma_px, -1.0).tolist()
    row["frame_chi2"] = [float(c) if np.isfinite(c) else None for c in found.chi2]
    row["dof"], row["passes"] = found.dof, found.passes
    chi2 = found.chi2[np.isfinite(found.chi2)]
    row["chi2_per_dof"] = float(chi2.sum() / (found.dof * max(len(chi2), 1)))
    return row


def summary(result: dict, sigma_scale: float = 1.0) -> list[str]:
    """Lines of a table over the rows of ``result`` (:func:`measure`'s, by ``SET/NAME``) that hold
    per-frame errors, grouped by set and by what ``shake.py`` added to the recording's name
    (``_shake0_flat0.1``): the largest move, the frames that registered more than ``STILL_PX``
    off at their worst corner, the frames refused, the lowest correlation, the RMS corner and
    centre errors, and the RMS corner error over the RMS standard error (each standard error
    times ``sigma_scale``: the factor it would take, against the one it was made with)."""
    groups = {}
    for key, row in result.items():
        if "corner_errors_px" not in row:
            continue
        folder, name = key.rsplit("/", 1)
        suffix = name[name.index("_shake"):] if "_shake" in name else ""
        groups.setdefault((folder, suffix), []).append(row)
    lines = ["| set | folders | largest move, px | frames registered > STILL_PX off | refused | lowest "
             "correlation | corner error RMS, px | centre error RMS, px | corner error / standard error |",
             "|---|---|---|---|---|---|---|---|---|"]
    for (folder, suffix), rows in sorted(groups.items()):
        largest = [r["largest_px"] for r in rows]
        off = sum(int(e > STILL_PX and g) for r in rows for e, g in zip(r["frame_corner_error_px"], r["frame_registered"]))
        errors = np.concatenate([np.ravel(r["corner_errors_px"]) for r in rows])
        sigmas = np.concatenate([np.ravel(r["corner_sigma_px"]) for r in rows]) * sigma_scale
        known = sigmas > 0
        correlation = min(c for r in rows for c in r["frame_correlation"] if c is not None)
        centre = [r["centre_error_rms_px"] for r in rows if "centre_error_rms_px" in r]
        lines.append(
            f"| {Path(folder).name}{suffix} | {len(rows)} | {min(largest):.3f}-{max(largest):.3f} | {off} | "
            f"{sum(r['refused'] for r in rows)} | {correlation:.4f} | {np.sqrt((errors ** 2).mean()):.3f} | "
            + (f"{min(centre):.3f}-{max(centre):.3f}" if centre else "-") + " | "
            f"{np.sqrt((errors[known] ** 2).mean() / (sigmas[known] ** 2).mean()):.2f} |")
    return lines


def timing(sets: list[str], passes: int, repeats: int) -> None:
    """Print, per recording of ``sets``, the median ratio of the registration's time to its time
    held to ``passes`` passes, the two alternated ``repeats`` times, and the median over them."""
    import time

    import cv2

    cv2.setNumThreads(1)  # with OMP_NUM_THREADS=1 for numpy's, the registration runs on one thread
    ratios = []
    for name in sets:
        for recording in recordings(name):
            frames, _ = _read_video(recording / "video.mp4", 0, None)
            camera = Camera.from_file(recording / "camera.json")
            spent = {"default": [], "held": []}
            for _ in range(repeats):
                for kind, limit in (("default", MOTION_MAX_PASSES), ("held", passes)):
                    start = time.perf_counter()
                    found = camera_motion(frames, camera, max_passes=limit)
                    spent[kind].append(time.perf_counter() - start)
                    if kind == "default":
                        ran = found.passes
            ratio = float(np.median(spent["default"]) / np.median(spent["held"]))
            ratios.append(ratio)
            print(f"{name}/{recording.name}: {np.median(spent['default']):.2f} s ({ran} passes) against "
                  f"{np.median(spent['held']):.2f} s held to {passes}: {ratio:.2f} times", flush=True)
    print(f"median over {len(ratios)} recordings: {np.median(ratios):.2f} times ({min(ratios):.2f}-{max(ratios):.2f})")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sets", nargs="*", help="folders of recordings (beside this file or paths)")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "camera_motion.json")
    ap.add_argument("--min-correlation", type=float, default=MOTION_MIN_CORRELATION,
                    help="the registration's floor (torchfit.video.MOTION_MIN_CORRELATION)")
    ap.add_argument("--time-against-passes", type=int, default=None, metavar="N",
                    help="time the registration against itself held to N passes (and stop)")
    ap.add_argument("--repeats", type=int, default=3, help="with --time-against-passes: alternations per recording")
    ap.add_argument("--summary", action="store_true", help="print the table of --out's rows (summary) and stop")
    ap.add_argument("--sigma-scale", type=float, default=1.0,
                    help="with --summary: scale the stored standard errors by this (they hold MOTION_SIGMA_FACTOR's value then)")
    args = ap.parse_args(argv)
    result = json.loads(args.out.read_text()) if args.out.exists() else {}
    if args.summary:
        print("\n".join(summary(result, args.sigma_scale)))
        return
    if args.time_against_passes is not None:
        timing(args.sets, args.time_against_passes, args.repeats)
        return
    for name in args.sets:
        for recording in recordings(name):
            row = measure(recording, args.min_correlation)
            result[f"{name}/{recording.name}"] = row
            print(name, recording.name, " ".join(f"{k} {v:.3f}" for k, v in row.items() if not isinstance(v, list)),
                  flush=True)
        args.out.write_text(json.dumps(result, indent=1))
    still = [r["largest_px"] for r in result.values() if "shake_rms_px" not in r]
    if still:
        print(f"{len(still)} without a shake: largest move {max(still):.3f} px (median {np.median(still):.3f});"
              f" STILL_PX {STILL_PX}")


if __name__ == "__main__":
    main()
