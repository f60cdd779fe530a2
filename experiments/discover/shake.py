"""A camera that is not quite still: a concealed recording refilmed with a small shake.

    python experiments/discover/shake.py SET NAME AMPLITUDE... [--out DIR] [--seed S] [--undo] [--roll DEG] [--turn DEG] [--flatten C]
    python -m torchfit experiment=discover_video data.video=DIR/NAME_shakeA/video.mp4 \
        object.mesh=DIR/NAME_shakeA/mesh.obj object.density=D camera.file=DIR/NAME_shakeA/camera.json

Each frame of ``SET/NAME/video.mp4`` (a folder beside this file, e.g. ``recordings``) is moved as a
whole by a smooth random offset: white noise in x and y, Gaussian-smoothed over
:data:`SMOOTH_FRAMES` frames and scaled to an RMS of ``AMPLITUDE`` px on each axis (seed ``S`` plus
a hash of the name, the same for every amplitude), resampled with Lanczos and stored again
through the recording's own codec and crf (``make_recordings.VideoWriter``). Amplitude 0 is the
second encoding alone. Each amplitude's folder ``DIR/NAME_shake<A>/`` gets the video, the
recording's ``mesh.obj``, ``camera.json`` and ``truth.json``, and ``shake.json`` with the offsets.
A move of the whole image is what a small turn of the camera does to a far background and, to
first order, to the object (HISTORY.md, *A camera that is not quite still*).

``--roll DEG`` turns each frame about the image centre as well, by a smooth random angle of
``DEG`` degrees RMS (made like the offsets, from its own seed): a camera that also turns about
its line of sight. Folders ``NAME_shake<A>_roll<DEG>/``; ``shake.json`` holds the angles too.

``--turn DEG`` turns the camera itself about its own centre: a pan and a tilt of ``DEG`` degrees
RMS each (and the ``--roll`` about its axis), made like the offsets, so each frame is the
still one seen through the homography ``K R K^-1`` of the recording's own ``camera.json``
(then moved by the offsets). A camera held in the hand turns this way, and
``torchfit.video.camera_motion`` measures such a homography; a shift and a turn of the picture
is its first-order part, exact at the principal point and off by ``angle * r^2 / f`` at a
distance ``r`` from it. Folders
``NAME_shake<A>[_roll<DEG>]_turn<DEG>/``; ``shake.json`` holds each frame's map
(``maps``, 3 x 3, a still pixel to the frame's).

``--flatten C`` first scales the texture of the background by ``C`` (0 to 1), as if the scene
were a plainer wall: each frame becomes ``frame - (1 - C) w (B - B_low)``, with ``B`` the
recording's median frame (its still background), ``B_low`` that blurred by
:data:`FLATTEN_SIGMA_PX` (the light's slow gradients stay) and ``w`` 1 away from the object
(its true mask from ``masks.npz``, or where the frame lies more than
:data:`FLATTEN_OBJECT_DIFF` grey levels off ``B``, grown by :data:`FLATTEN_GROW_PX` and
feathered), 0 on it; the object and the codec's noise stay. Folders ``..._flat<C>/``
(HISTORY.md, *A background with little texture*).

``--undo`` also writes ``DIR/NAME_shake<A>[_roll<DEG>][_turn<DEG>]_undone/``: the refilmed video's
frames moved back by the shake's own maps (``torchfit.video.stabilised``) as lossless PNGs,
with the same files beside them. Run with ``data.fps=FPS data.segmentation.stabilise=false``, it shows what moving
the frames back costs when the offsets are exact.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import zlib
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "recordings"))  # make_recordings.VideoWriter

SMOOTH_FRAMES = 3.0  # the Gaussian's standard deviation, frames
FLATTEN_SIGMA_PX = 25.0  # --flatten keeps the background's variations broader than this
FLATTEN_OBJECT_DIFF = 10.0  # ... and leaves alone pixels this far off the background (the object, its blur)
FLATTEN_GROW_PX = 2  # ... grown by this much, and feathered by a third of it


def shake_path(frames: int, amplitude: float, seed: int) -> np.ndarray:
    """(T, 2) offsets in px: white noise smoothed by a Gaussian of :data:`SMOOTH_FRAMES` frames,
    each axis scaled to an RMS of ``amplitude`` about zero."""
    from scipy.ndimage import gaussian_filter1d

    noise = gaussian_filter1d(np.random.default_rng(seed).normal(size=(frames, 2)), SMOOTH_FRAMES, axis=0,
                              mode="reflect")
    noise -= noise.mean(0)
    return amplitude * noise / noise.std(0)


def shaken(frames: np.ndarray, offsets: np.ndarray, angles: np.ndarray | None = None) -> np.ndarray:
    """(T, H, W, 3) uint8 ``frames`` each turned by its angle (degrees, about the image centre;
    none when ``angles`` is None) and moved by its (2,) offset (x, y) in px, Lanczos, the border
    replicated."""
    from torchfit.video import _motion_matrices

    height, width = frames.shape[1:3]
    angles = np.zeros(len(frames)) if angles is None else angles
    maps = _motion_matrices(np.column_stack([offsets, angles]), (height, width))
    return np.stack([cv2.warpAffine(frame, warp[:2].astype(np.float32), (width, height), flags=cv2.INTER_LANCZOS4,
                                    borderMode=cv2.BORDER_REPLICATE) for frame, warp in zip(frames, maps)])


def flattened(frames: np.ndarray, masks: np.ndarray, amount: float) -> np.ndarray:
    """(T, H, W, 3) uint8 ``frames`` with their background's texture scaled by ``amount`` away
    from the object, whose (T, H, W) bool ``masks`` are given (see ``--flatten``)."""
    still = np.median(frames, axis=0).astype(np.float32)
    texture = still - cv2.GaussianBlur(still, (0, 0), FLATTEN_SIGMA_PX)
    grow = np.ones((2 * FLATTEN_GROW_PX + 1,) * 2, np.uint8)
    out = []
    for frame, mask in zip(frames, masks):
        near = mask | (np.abs(frame.astype(np.float32) - still).max(-1) > FLATTEN_OBJECT_DIFF)
        near = cv2.GaussianBlur(cv2.dilate(near.astype(np.uint8), grow).astype(np.float32), (0, 0),
                                FLATTEN_GROW_PX / 3)
        away = 1.0 - np.clip(near, 0.0, 1.0)
        out.append(np.clip(np.rint(frame - (1.0 - amount) * away[..., None] * texture), 0, 255).astype(np.uint8))
    return np.stack(out)


def shake_motion(shake: dict) -> np.ndarray:
    """(T, 3) the motion rows ``(dx, dy, turn)`` of a ``shake.json``'s content, as
    ``torchfit.video.camera_motion`` reads them (the same map as :func:`shaken`'s)."""
    offsets = np.asarray(shake["offsets_px"], float)
    turns = np.zeros(len(offsets)) if shake.get("roll_deg") is None else np.asarray(shake["roll_deg"], float)
    return np.column_stack([offsets, turns])


def turn_maps(offsets: np.ndarray, pan_tilt: np.ndarray, roll: np.ndarray, camera: dict) -> np.ndarray:
    """(T, 3, 3) maps of a still pixel to the frame's, for a camera turned by (T, 2) ``pan_tilt``
    and (T,) ``roll`` (degrees, about its y, x and optical axes, each by the right-hand rule with
    x right, y down, z into the scene) with the intrinsics of ``camera`` (``camera.json``'s
    content), then moved by (T, 2) ``offsets`` (px): ``K R K^-1`` with
    ``R = R_y(pan) R_x(tilt) R_z(roll)``. The roll turns the picture the other way from
    :func:`shaken`'s angle (clockwise on the screen for a positive one)."""
    k = np.array([[camera["fx"], 0.0, camera["cx"]], [0.0, camera["fy"], camera["cy"]], [0.0, 0.0, 1.0]])
    maps = []
    for (dx, dy), (pan, tilt), spin in zip(offsets, np.radians(pan_tilt), np.radians(roll)):
        c, s = np.cos(pan), np.sin(pan)
        r_y = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        c, s = np.cos(tilt), np.sin(tilt)
        r_x = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
        c, s = np.cos(spin), np.sin(spin)
        r_z = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        h = np.array([[1, 0, dx], [0, 1, dy], [0, 0, 1]]) @ k @ r_y @ r_x @ r_z @ np.linalg.inv(k)
        maps.append(h / h[2, 2])
    return np.stack(maps)


def shake_maps(shake: dict, size: tuple[int, int]) -> np.ndarray:
    """(T, 3, 3) each frame's map of a still pixel to the frame's, of a ``shake.json``'s content
    for frames of ``size`` ``(H, W)``: its ``maps`` where the camera was turned (``--turn``),
    else its shift and turn (:func:`shake_motion`)."""
    from torchfit.video import _motion_matrices

    return np.asarray(shake["maps"], float) if "maps" in shake else _motion_matrices(shake_motion(shake), size)


def store_like(path: Path, spec: dict, frames: np.ndarray) -> None:
    """(T, H, W, 3) uint8 BGR ``frames`` stored as the video ``path`` the way the recording whose
    truth.json ``spec`` is was stored: its codec, crf, stated frame rate and transfer tag
    (``make_recordings.VideoWriter``)."""
    import make_recordings as mr

    writer = mr.VideoWriter(path, SimpleNamespace(
        codec=spec["codec"], crf=spec["crf"], fps=spec["fps"], fps_stated=spec.get("fps_stated"),
        transfer=spec.get("transfer", "linear")), frames.shape[2], frames.shape[1])
    for frame in frames:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    writer.release()


def make(folder: Path, amplitude: float, out: Path, seed: int = 0, roll: float = 0.0, turn: float = 0.0,
         flatten: float = 1.0) -> Path:
    """The recording ``folder`` refilmed with a shake of ``amplitude`` px RMS (and a turn about the
    line of sight of ``roll`` degrees RMS; with ``turn``, the camera panned and tilted by that many
    degrees RMS each, :func:`turn_maps`) into ``out``, its background's texture first scaled by
    ``flatten`` (:func:`flattened`, when under 1); returns the new folder."""
    from torchfit.video import _read_video

    if not (amplitude >= 0):
        raise SystemExit(f"the shake's amplitude must be a number of pixels >= 0, got {amplitude}")
    truth = json.loads((folder / "truth.json").read_text())
    spec = truth["spec"]
    frames, _ = _read_video(folder / "video.mp4", 0, None)  # BGR
    if not (0 <= flatten <= 1):
        raise SystemExit(f"--flatten must lie between 0 and 1, got {flatten}")
    if flatten < 1:
        with np.load(folder / "masks.npz") as archive:
            frames = flattened(frames, archive["masks"], flatten)
    offsets = shake_path(len(frames), amplitude, seed + zlib.crc32(folder.name.encode()))
    angles = shake_path(len(frames), roll, seed + 1 + zlib.crc32(folder.name.encode()))[:, 0] if roll else None
    target = out / (f"{folder.name}_shake{amplitude:g}" + (f"_roll{roll:g}" if roll else "")
                    + (f"_turn{turn:g}" if turn else "") + (f"_flat{flatten:g}" if flatten < 1 else ""))
    target.mkdir(parents=True, exist_ok=True)
    record = {"source": str(folder), "amplitude_px": amplitude, "smooth_frames": SMOOTH_FRAMES,
              "offsets_px": offsets.tolist(), "roll_deg": None if angles is None else angles.tolist(),
              "flatten": flatten}
    if turn:
        pan_tilt = shake_path(len(frames), turn, seed + 2 + zlib.crc32(folder.name.encode()))
        maps = turn_maps(offsets, pan_tilt, np.zeros(len(frames)) if angles is None else angles,
                         json.loads((folder / "camera.json").read_text()))
        height, width = frames.shape[1:3]
        moved = np.stack([cv2.warpPerspective(frame, h, (width, height), flags=cv2.INTER_LANCZOS4,
                                              borderMode=cv2.BORDER_REPLICATE) for frame, h in zip(frames, maps)])
        record |= {"turn_deg": pan_tilt.tolist(), "maps": maps.tolist()}
    else:
        moved = shaken(frames, offsets, angles)
    store_like(target / "video.mp4", spec, moved)
    for name in ("mesh.obj", "camera.json", "truth.json"):
        shutil.copy(folder / name, target / name)
    (target / "shake.json").write_text(json.dumps(record))
    return target


def undo(target: Path) -> Path:
    """The refilmed recording ``target``'s frames moved back by its shake's own maps (:func:`shake_maps`),
    as PNGs in ``<target>_undone/`` with its other files; returns that folder."""
    from torchfit.video import _read_video, stabilised

    frames, _ = _read_video(target / "video.mp4", 0, None)
    maps = shake_maps(json.loads((target / "shake.json").read_text()), frames.shape[1:3])
    undone = target.with_name(target.name + "_undone")
    undone.mkdir(exist_ok=True)
    for t, frame in enumerate(stabilised(frames, maps)):
        cv2.imwrite(str(undone / f"{t:03d}.png"), frame)
    for name in ("mesh.obj", "camera.json", "truth.json", "shake.json"):
        shutil.copy(target / name, undone / name)
    return undone


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("set", help="a folder of concealed recordings beside this file (recordings, recordings_fresh2)")
    ap.add_argument("name", help="the recording")
    ap.add_argument("amplitudes", type=float, nargs="+", help="RMS of the shake on each axis, px")
    ap.add_argument("--out", type=Path, default=HERE / "recordings_shake", help="where the refilmed folders go")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--undo", action="store_true", help="also the frames moved back by the shake's own motion (PNGs)")
    ap.add_argument("--roll", type=float, default=0.0, metavar="DEG",
                    help="also turn each frame about the image centre, DEG degrees RMS")
    ap.add_argument("--turn", type=float, default=0.0, metavar="DEG",
                    help="also pan and tilt the camera, DEG degrees RMS each (a homography)")
    ap.add_argument("--flatten", type=float, default=1.0, metavar="C",
                    help="first scale the background's texture by C (0 to 1): a plainer wall")
    args = ap.parse_args(argv)
    folder = HERE / args.set / args.name
    if not (folder / "truth.json").exists():
        raise SystemExit(f"no concealed recording {folder}: make it with make_concealed.py")
    for amplitude in args.amplitudes:
        target = make(folder, amplitude, args.out, args.seed, args.roll, args.turn, args.flatten)
        print(target, flush=True)
        if args.undo:
            print(undo(target), flush=True)


if __name__ == "__main__":
    main()
