#!/usr/bin/env python
"""The concealed set: MuJoCo recordings that each hide one effect (or none) from the baseline model.

Issue 6 ("Missing physics") asks for test recordings from the independent engine where an effect
is real but concealed: the baseline (vacuum, uniform density, stated fps, pinhole camera) fit
alone should still look good, while the effect leaves a residual. Each recording's
``truth.json`` holds the ground truth of the usual recordings plus ``effects``:
``{vocabulary name: {torchfit parameter: value}}`` (``{}`` for the controls), with parameter names
as in ``torchfit.effects.EFFECTS`` so ``make_effect(name, area=shape.reference_area, **params)``
rebuilds each. See CONCEALED.md for what each recording hides and how big it is.

Make them all (from the repository root, ~2 minutes on one core)::

    MUJOCO_GL=osmesa python experiments/discover/make_concealed.py

Options: ``--out DIR`` (default experiments/discover/recordings, git-ignored), ``--only a,b``,
``--list``, ``--markdown`` (print the table as Markdown, as in CONCEALED.md), ``--fresh K``
(a fresh set from the same recipes: other seeds and background scene K, in recordings_fresh<K>/),
``--shutter`` (the four controls' throws through a rolling shutter, and the controls, in
recordings_shutter/: ``shutter_specs``), ``--sharp`` (the set without motion blur: one render per frame
at its time, in recordings[_fresh<K>]_sharp/; everything else as in the set), ``--crf C`` (the set
encoded at H.264 quality C instead of 14, in recordings[_fresh<K>]_crf<C>/: how the compression
moves the verdicts), ``--scale N`` (the set through a camera with N times the pixels along each
side, the same lens and throws, in recordings[_fresh<K>]_x<N>/), ``--fps-scale N`` (the same
throws filmed at N times the frame rate, each frame exposed for the same fraction of its interval,
in recordings[_fresh<K>]_fps<N>/; ``--fps-scale 1/N``: one frame in N, each exposed N times as
long, in ..._fps1by<N>/; ``--fps-scale 5/6``: 50 fps, frames between the set's, in
..._fps5by6/), ``--plain`` (the same throws in front of a plain wall and floor
with no cabinet or crate, little for the camera's registration to hold on to, in
recordings[_fresh<K>]..._plain/).

The "effect size" column is measured, not assumed: the same throw (same initial state) is
simulated again without the effect (vacuum / no weight / the stated clock / a distortion-free
lens) and the two silhouettes' centroids are compared, in pixels, at the last frame and at worst.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "recordings"))
import make_recordings as mr
from true_masks import fps_factor, fresh_folder

SHUTTER_OUT = HERE / "recordings_shutter"

# Aerodynamics: MuJoCo's ellipsoid fluid model on an invisible massless sphere of the shape's
# reference area at the centre of mass (exactly torchfit's quadratic_drag + magnus, see
# make_recordings.fluid_truth). Viscosity and angular drag off (no exact torchfit counterpart,
# and the Stokes terms are ~1e-3 of the quadratic drag anyway); air density = torchfit's 1.2.
# C_M = 1/2 cancels MuJoCo's added-mass lift on a sphere, so "drag" recordings have no lift;
# "magnus" recordings have no drag (blunt = 0), so every recording hides exactly one effect.
AIR = {"fluid": True, "fluid_sphere": True, "fluid_density": 1.2, "fluid_viscosity": 0.0}


def drag(blunt: float) -> dict:
    """C_d = 2 * blunt (torchfit convention), no lift."""
    return {**AIR, "fluidcoef": (blunt, 0.25, 0.0, 1.0, 0.5)}


def lift(magnus: float) -> dict:
    """C_L = 8/3 (C_M - 1/2) per unit spin ratio (torchfit convention), no drag."""
    return {**AIR, "fluidcoef": (0.0, 0.0, 0.0, 1.0, magnus)}


def concealed_specs(fresh: int = 0) -> list[tuple[mr.RecordingSpec, str]]:
    """(spec, what it hides) for every recording of the concealed set.

    ``fresh`` > 0 gives a fresh set: the same recipes (objects, effects and their sizes, camera,
    frame counts) with every seed moved by 1000 * fresh, so other throws, spins and sensor noise,
    and background scene ``fresh`` instead of 0 (the shipped recordings and the first set use 0).
    """
    def S(**kw):
        kw["seed"] += 1000 * fresh
        return mr.RecordingSpec(scene_seed=fresh, **kw)
    base = {"write_effects": True, "n_frames": 45, "fps": 60.0}
    tennis = {"shape": "sphere", "ball_radius": 0.033, "density": 380.0}  # 57 g, a tennis ball
    foam = {"shape": "sphere", "ball_radius": 0.035, "density": 150.0}  # 27 g foam ball
    # a ball shows no rotation, so over 0.75 s its drag is a constant deceleration that a tilted
    # gravity and a changed initial velocity absorb (discover measured 0.28 px held-out error):
    # the ball throws last 0.9 s (farther away to stay in view), long enough for the deceleration to
    # turn with the velocity
    long = {**base, "n_frames": 54, "depth_range": (1.9, 2.4), "max_tries": 2000}
    # a ball's lift: its spin is hidden from video, so only the lift vector C_L w is measured
    # (added 2026-11-29, thirty-fifth session; HISTORY.md); its control is the same throw and spin
    # without the lift
    spinning_ball = S(name="magnus_ball", **foam, **lift(1.0), spin_rate=40.0, spin_axis="random",
                      tilt_deg=6.0, roll_deg=3.0, seed=161, **long)
    return [
        # ---- quadratic drag ----
        (S(name="drag_ball", **tennis, **drag(0.25), spin_rate=0.0, tilt_deg=8.0, roll_deg=3.0,
           seed=101, **long), "quadratic drag, tennis ball (C_d 0.5)"),
        (S(name="drag_foam_ball", **foam, **drag(0.25), spin_rate=0.0, tilt_deg=5.0,
           roll_deg=-4.0, seed=102, **long),
         "quadratic drag, light foam ball (C_d 0.5)"),
        (S(name="drag_tshape", shape="tshape", **drag(0.4), spin_rate=8.0, spin_axis="major",
           spin_wobble=0.3, tilt_deg=10.0, roll_deg=5.0, seed=103, **base),
         "quadratic drag, T-handle (C_d 0.8)"),
        # added after the first run showed that a ball's drag is absorbed (no visible rotation)
        (S(name="drag_box", shape="box", **drag(0.4), spin_rate=9.0, spin_axis="random", tilt_deg=6.0,
           roll_deg=-3.0, seed=104, **base), "quadratic drag, box (C_d 0.8)"),
        # drag_ball and drag_box hide a drag below what their clips can show (discover's detection
        # limit on them: C_d 1.0 and 1.29 on the segmented video, 0.63 and 0.96 on the true masks,
        # for 0.5 and 0.8 hidden); they stay as they are. These two are the same throws with a
        # quarter of the mass (a 14 g foam practice ball, a 150 kg/m^3 cardboard box): the drag's
        # deceleration, and so its signal, is 4x, the limit ~1/4 (~0.25 and ~0.32 segmented)
        (S(name="drag_light_ball", **{**tennis, "density": 95.0}, **drag(0.25), spin_rate=0.0,
           tilt_deg=8.0, roll_deg=3.0, seed=101, **long),
         "quadratic drag, drag_ball's throw with 1/4 of the mass (C_d 0.5)"),
        (S(name="drag_light_box", shape="box", density=150.0, **drag(0.4), spin_rate=9.0,
           spin_axis="random", tilt_deg=6.0, roll_deg=-3.0, seed=104, **base),
         "quadratic drag, drag_box's throw with 1/4 of the mass (C_d 0.8)"),
        # ---- Magnus lift (visible spin: bodies whose rotation the silhouette shows) ----
        (S(name="magnus_tshape", shape="tshape", **lift(1.0), spin_rate=16.0, spin_axis="major",
           spin_wobble=0.15, tilt_deg=9.0, roll_deg=-3.0, seed=111, **base),
         "Magnus lift, T-handle spinning about its major axis"),
        (S(name="magnus_cylinder", shape="cylinder", **lift(1.0), spin_rate=25.0,
           spin_axis="major", spin_wobble=0.2, tilt_deg=7.0, roll_deg=4.0, seed=112, **long),
         "Magnus lift, cylinder tumbling end over end"),
        (spinning_ball, "Magnus lift, foam ball spinning at 40 rad/s"),
        # ---- centre of mass moved by a hidden dense block ----
        # com_tshape, time_tshape and lens_tshape were first made stronger (36 g, 58.5 fps, k1 -0.15):
        # their baselines were visibly off (mean IoU 0.885, 0.862, 0.773), not concealed
        (S(name="com_tshape", shape="tshape", hidden_weight=((0.05, 0.0, 0.0), (0.008,) * 3, 0.024),
           spin_rate=10.0, spin_axis="major", spin_wobble=0.3, tilt_deg=10.0, roll_deg=-5.0,
           seed=121, **base), "centre of mass: 24 g block inside one crossbar arm"),
        (S(name="com_cylinder", shape="cylinder",
           hidden_weight=((0.0, 0.0, 0.07), (0.01,) * 3, 0.066), spin_rate=10.0,
           spin_axis="major", spin_wobble=0.25, tilt_deg=6.0, roll_deg=6.0,
           depth_range=(1.4, 1.7), seed=122, **base),
         "centre of mass: 66 g block near one end"),
        # ---- wrong frame rate: container fps != true fps ----
        (S(name="time_tshape", shape="tshape", fps_stated=59.2, spin_rate=10.0, spin_axis="major",
           spin_wobble=0.3, tilt_deg=10.0, roll_deg=2.0, seed=131,
           **{**base, "fps": 60.0}), "clock: 60 fps stated as 59.2"),
        (S(name="time_box", shape="box", fps_stated=60.0, spin_rate=12.0, spin_axis="random",
           tilt_deg=12.0, roll_deg=-3.0, seed=132, **{**base, "fps": 58.5}),
         "clock: 58.5 fps stated as 60"),
        # ---- lens distortion missing from camera.json; throws across the whole width ----
        # (min_iou 0.94: the generator's own check of its masks, the numpy rasteriser against
        # MuJoCo's render resampled through the distortion, passed a thin T-handle at 0.947 in its
        # worst frame while the masks were resampled by nearest neighbour; since their supersampled
        # resampling (make_recordings.LENS_MASK_SUPERSAMPLE, 2026-11-26) the worst of all eight lens
        # recordings is 0.985, and the bound is kept so the recordings stay as they were made)
        (S(name="lens_tshape", shape="tshape", distortion=(-0.08, 0.01), u_start=(0.07, 0.1),
           u_end=(0.9, 0.93), spin_rate=9.0, spin_axis="major", spin_wobble=0.3, tilt_deg=8.0,
           roll_deg=4.0, depth_range=(1.3, 1.5), seed=141, min_iou=0.94, **base),
         "barrel distortion k1 -0.08, k2 0.01"),
        (S(name="lens_box", shape="box", distortion=(-0.2, 0.04), u_start=(0.07, 0.1),
           u_end=(0.9, 0.93), spin_rate=10.0, spin_axis="random", tilt_deg=10.0, roll_deg=-6.0,
           depth_range=(1.3, 1.5), seed=142, min_iou=0.94, **base),
         "barrel distortion k1 -0.2, k2 0.04"),
        # ---- controls: nothing missing ----
        (S(name="control_tshape", shape="tshape", spin_rate=10.0, spin_axis="major",
           spin_wobble=0.3, tilt_deg=9.0, roll_deg=3.0, seed=151, **base), "nothing (control)"),
        (S(name="control_box", shape="box", spin_rate=15.0, spin_axis="random", tilt_deg=11.0,
           roll_deg=-2.0, seed=152, **base), "nothing (control)"),
        (S(name="control_cylinder", shape="cylinder", spin_rate=6.0, spin_axis="random",
           tilt_deg=6.0, roll_deg=-5.0, depth_range=(1.5, 1.8), seed=153, **base),
         "nothing (control)"),
        (S(name="control_ball", **tennis, spin_rate=0.0, tilt_deg=7.0, roll_deg=2.0, seed=154,
           **base), "nothing (control)"),
        (twin_spec(spinning_ball).replace(name="control_spinning_ball"),
         "nothing (control): magnus_ball's throw and spin without the lift"),
    ]


SHUTTER_DELAYS = {"tshape": 3e-5, "box": 3e-5, "cylinder": 2e-5, "ball": 2e-5}  # seconds per row


def shutter_specs() -> list[tuple[mr.RecordingSpec, str]]:
    """The rolling-shutter set: the four controls' throws of the first set (the same specs and
    seeds, so the same flights) through a rolling shutter (``SHUTTER_DELAYS``: 30 µs per row for
    the T-handle and the box, 14 ms to read the 480 rows, a phone's readout at 30-60 fps; 20 µs
    for the cylinder and the ball), each followed by its control."""
    controls = {s.name: (s, what) for s, what in concealed_specs(0)}
    out = []
    for shape, delay in SHUTTER_DELAYS.items():
        spec, what = controls[f"control_{shape}"]
        out.append((spec.replace(name=f"shutter_{shape}", line_delay=delay),
                    f"rolling shutter {delay * 1e6:.0f} us/row, control_{shape}'s throw"))
        out.append((spec, what))
    return out


def scaled_spec(spec: mr.RecordingSpec, scale: int) -> mr.RecordingSpec:
    """The same recording through a camera with ``scale`` times the pixels along each side: the
    same field of view (so the focal length in pixels scales too), and the in-view margin scaled
    with the pixels, so that the same throw is drawn and kept."""
    return spec.replace(width=spec.width * scale, height=spec.height * scale, margin_px=spec.margin_px * scale)


def fps_scaled_spec(spec: mr.RecordingSpec, factor: Fraction | int) -> mr.RecordingSpec:
    """The same recording filmed at ``factor`` times the frame rate (any positive fraction): the
    same flight over the same seconds (the last frame dropped where the new interval does not
    divide them), each frame exposed for the same fraction of its interval, as a camera with a
    fixed shutter angle does; a wrong clock is stated at ``factor`` times its rate. At ``N`` times,
    ``N - 1`` frames lie between each two of the original (so its frames are every ``N``-th of
    these), blurred by as many sub-frames as the set's; at ``1/N``, the frames are every ``N``-th
    of the original's; below 1 each frame is exposed ``1 / factor`` times as long and blurred by
    sub-frames spaced in time about as the set's are (exactly at ``1/N``). At ``5/6`` (50 fps) and
    ``5/12`` (25 fps) the frames fall between the set's.
    The throw is the set's, drawn at the set's frame rate and pinned (``position`` ...
    ``angular_velocity``): the frames in between are only asked to stay in the image
    (``margin_px`` 0), since the set's margin, checked at more instants, would turn some throws
    away and draw others."""
    factor = Fraction(factor)
    if factor == 1:
        return spec
    mesh = mr.make_mesh(spec.shape, spec.ball_radius)
    (p, q, v, w), _ = mr.resolve_ic(spec, mr.Scene(spec, mesh), mesh)
    n_frames = math.floor((spec.n_frames - 1) * factor) + 1
    subframes = spec.blur_subframes if factor >= 1 else round((spec.blur_subframes - 1) / factor) + 1
    return spec.replace(fps=float(spec.fps * factor), n_frames=n_frames, blur_subframes=subframes,
                        fps_stated=None if spec.fps_stated is None else float(spec.fps_stated * factor),
                        position=tuple(map(float, p)), orientation_wxyz=tuple(map(float, q)),
                        velocity=tuple(map(float, v)), angular_velocity=tuple(map(float, w)), margin_px=0)


def twin_spec(spec: mr.RecordingSpec) -> mr.RecordingSpec:
    """The same recording without its hidden effect."""
    return spec.replace(fluid=False, fluid_sphere=False, fluidcoef=None, hidden_weight=None,
                        fps_stated=None, distortion=None, line_delay=None)


def _centroids(masks) -> np.ndarray:
    out = []
    for m in masks:
        ys, xs = np.nonzero(m)
        out.append([xs.mean(), ys.mean()])
    return np.asarray(out)


def effect_size(spec: mr.RecordingSpec, folder: Path) -> dict:
    """Centroid shift (px) between the recording's true masks and its effect-free twin.

    The twin starts from the same state (truth params). Force / body effects: simulated again
    without them. Clock: the same flight sampled at the stated frame times i / fps_stated.
    Lens: the same poses projected without distortion. Rolling shutter: the flight at the frame
    times (a global shutter). Twin masks are the mesh projected with the
    numpy rasteriser of make_recordings (matches MuJoCo's masks to IoU >= 0.95, ~0.05 px).
    """
    truth = json.loads((folder / "truth.json").read_text())
    with np.load(folder / "masks.npz") as z:
        masks = z["masks"].astype(bool)
    mesh = mr.make_mesh(spec.shape, spec.ball_radius)
    V, F = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    cam = mr.camera_intrinsics(spec.width, spec.height, spec.fovy_deg)
    p = truth["params"]
    ic = (np.asarray(p["position"]), np.asarray(p["orientation_wxyz"]), np.asarray(p["velocity"]),
          np.asarray(p["angular_velocity"]))
    n = spec.n_frames
    if spec.distortion is not None:
        poses = list(zip(truth["per_frame"]["R"], truth["per_frame"]["position"]))
    else:
        twin = twin_spec(spec)
        scene = mr.Scene(twin, mesh)
        fps = spec.fps if spec.fps_stated is None else spec.fps_stated
        qpos = scene.simulate(ic, np.arange(n) / fps)
        poses = [scene.pose_cam(q) for q in qpos]
    twin_masks = [mr.render_silhouette(V, F, np.asarray(R), np.asarray(t), cam) for R, t in poses]
    shift = np.linalg.norm(_centroids(masks) - _centroids(twin_masks), axis=1)
    radius = float(np.sqrt(masks.sum((1, 2)).mean() / np.pi))
    return {"last_px": float(shift[-1]), "max_px": float(shift.max()),
            "object_radius_px": radius}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=None, help="output folder (default recordings/, or recordings_fresh<K>/)")
    ap.add_argument("--fresh", type=int, default=0, metavar="K",
                    help="a fresh set: seeds moved by 1000 K, background scene K (K >= 1)")
    ap.add_argument("--shutter", action="store_true",
                    help="the rolling-shutter set (shutter_specs) in recordings_shutter/")
    ap.add_argument("--sharp", action="store_true",
                    help="without motion blur (one render per frame), in recordings[_fresh<K>]_sharp/")
    ap.add_argument("--crf", type=int, default=None, metavar="C",
                    help="H.264 constant rate factor C (0-51) instead of 14, in recordings[_fresh<K>]_crf<C>/")
    ap.add_argument("--transfer", choices=("srgb", "bt709"), default=None,
                    help="store the frames through this camera curve (the light summed first), in "
                         "recordings[_fresh<K>]_<curve>/ (segment with SegmentationSettings.transfer)")
    ap.add_argument("--scale", type=int, default=1, metavar="N",
                    help="a camera with N times the pixels along each side (the same lens and field of view, "
                         "the same throws), in recordings[_fresh<K>]_x<N>/")
    ap.add_argument("--fps-scale", type=fps_factor, default=Fraction(1), metavar="N|1/N|P/Q",
                    help="the same throws filmed at this many times the frame rate (the same seconds, the exposure "
                         "the same fraction of each frame's interval), in recordings[_fresh<K>]_fps<N>/ "
                         "(_fps1by<N>/, _fps<P>by<Q>/; 5/6 is 50 fps)")
    ap.add_argument("--plain", action="store_true",
                    help="the same throws in front of a plain wall and floor, no cabinet or crate "
                         "(RecordingSpec.plain_scene), in recordings[_fresh<K>]..._plain/")
    ap.add_argument("--only", action="append", default=[], help="names (repeatable / a,b)")
    ap.add_argument("--list", action="store_true", help="list the specs and exit")
    ap.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    args = ap.parse_args(argv)
    mr.offscreen_gl()
    if args.fresh < 0:
        raise SystemExit(f"--fresh must be >= 0, got {args.fresh}")
    if args.sharp and args.shutter:
        raise SystemExit("--sharp is a concealed set without motion blur: not with --shutter")
    if args.crf is not None and (args.shutter or args.sharp or not 0 <= args.crf <= 51):
        raise SystemExit(f"--crf needs an H.264 quality 0-51 (not with --shutter or --sharp), got {args.crf}")
    if args.scale < 1 or (args.scale != 1 and args.shutter):
        raise SystemExit(f"--scale needs a whole factor >= 1 on a concealed set (not with --shutter), got {args.scale}")
    if args.fps_scale != 1 and args.shutter:
        raise SystemExit(f"--fps-scale is a concealed set's frame rate: not with --shutter, got {args.fps_scale}")
    if args.transfer is not None and args.shutter:
        raise SystemExit("--transfer makes a concealed set: not with --shutter")
    specs = shutter_specs() if args.shutter else concealed_specs(args.fresh)
    if args.list:
        for s, what in specs:
            print(f"{s.name:18s} {what}")
        return 0
    only = {n for o in args.only for n in o.split(",") if n}
    if only:
        unknown = only - {s.name for s, _ in specs}
        if unknown:
            raise SystemExit(f"unknown recording(s) {sorted(unknown)}; valid: {[s.name for s, _ in specs]}")
        specs = [(s, w) for s, w in specs if s.name in only]
    # only the recordings to be made: a faster clock pins each throw, which draws it first
    specs = [(fps_scaled_spec(scaled_spec(s, args.scale), args.fps_scale), what) for s, what in specs]
    if args.crf is not None:
        specs = [(s.replace(crf=args.crf), what) for s, what in specs]
    if args.sharp:
        specs = [(sharp_spec(s), what) for s, what in specs]
    if args.transfer is not None:
        specs = [(s.replace(transfer=args.transfer), what) for s, what in specs]
    if args.plain:
        specs = [(s.replace(plain_scene=True), what) for s, what in specs]
    out = Path(args.out) if args.out else (SHUTTER_OUT if args.shutter else fresh_folder(
        args.fresh, args.sharp, args.crf, args.transfer, args.scale, args.fps_scale, args.plain))
    rows = []
    for spec, what in specs:
        summary = mr.make_recording(spec, out)
        truth = json.loads((out / spec.name / "truth.json").read_text())
        size = effect_size(spec, out / spec.name)
        rows.append({"name": spec.name, "hides": what, "effects": truth["effects"],
                     "shape": spec.shape, "size": f"{spec.width}x{spec.height}x{spec.n_frames}",
                     "iou_min_check": summary["iou_min"], **size})
    summary_file = out / "concealed_summary.json"  # --only updates its rows, keeps the others
    kept = json.loads(summary_file.read_text()) if summary_file.exists() else []
    summary_file.write_text(json.dumps(merge_summary(kept, rows), indent=1))
    print()
    if args.markdown:
        print("| recording | hides | truth (torchfit parameters) | shift last frame (px) "
              "| worst (px) | object radius (px) |")
        print("|---|---|---|---|---|---|")
    for r in rows:
        eff = "; ".join(f"{k}: " + ", ".join(f"{p}={_fmt(v)}" for p, v in d.items())
                        for k, d in r["effects"].items()) or "{}"
        if args.markdown:
            print(f"| {r['name']} | {r['hides']} | {eff} | {r['last_px']:.1f} | {r['max_px']:.1f} "
                  f"| {r['object_radius_px']:.0f} |")
        else:
            print(f"{r['name']:18s} {r['last_px']:6.1f} px (worst {r['max_px']:5.1f})  "
                  f"r={r['object_radius_px']:3.0f} px  {eff}")
    return 0


def sharp_spec(spec: mr.RecordingSpec) -> mr.RecordingSpec:
    """The same recording without motion blur: one render per frame, at the frame's time."""
    return spec.replace(blur_subframes=1)


def merge_summary(kept: list[dict], made: list[dict]) -> list[dict]:
    """Summary rows: ``made`` replaces the rows of ``kept`` with the same name; spec order."""
    names = {r["name"] for r in made}
    order = [s.name for s, _ in concealed_specs()]
    merged = [r for r in kept if r["name"] not in names] + made
    return sorted(merged, key=lambda r: order.index(r["name"]) if r["name"] in order else len(order))


def _fmt(v) -> str:
    if isinstance(v, list):
        return "(" + ", ".join(f"{x * 1000:.1f}" for x in v) + ") mm"
    return f"{v:.4g}"


if __name__ == "__main__":
    sys.exit(main())
