"""The concealed set (experiments/discover/make_concealed.py): hidden effects and their truth.

The first test runs by default when MuJoCo is installed (a few seconds, no rendering): it checks
the derivation of the engine's drag and lift coefficients in torchfit's conventions by flying the
same throw in MuJoCo (ellipsoid fluid model) and in torchfit's integrator with the derived
effects. The others render small versions of the recordings and are marked ``recordings``.
"""
from __future__ import annotations

import importlib.util
import json
import math
import sys
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchfit.search import SearchSettings

ROOT = Path(__file__).resolve().parents[1]
RECORDINGS = ROOT / "experiments" / "recordings"
CONCEALED = ROOT / "experiments" / "discover" / "make_concealed.py"


def _load(name: str, path: Path):
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses need the module registered
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def mods():
    sys.path.insert(0, str(RECORDINGS))
    mr = _load("make_recordings", RECORDINGS / "make_recordings.py")
    mr.offscreen_gl()  # before mujoco is imported
    pytest.importorskip("mujoco")
    sys.path.insert(0, str(CONCEALED.parent))  # make_concealed.py imports true_masks from its folder
    mc = _load("make_concealed", CONCEALED)
    return mr, mc


@pytest.mark.parametrize("name", ["drag_ball", "drag_tshape", "magnus_tshape"])
def test_engine_coefficients_reproduce_mujoco_flight(mods, tmp_path, name):
    """MuJoCo with fluid forces vs torchfit.integrate with quadratic_drag / magnus at the derived
    coefficients: same trajectory to 1e-4 of the fluid's own effect (measured ~1e-8)."""
    from torchfit.dynamics import RigidBody, integrate
    from torchfit.effects import make_effect
    from torchfit.shape import load_shape

    mr, mc = mods
    spec = next(s for s, _ in mc.concealed_specs() if s.name == name)
    mesh = mr.make_mesh(spec.shape, spec.ball_radius)
    scene = mr.Scene(spec, mesh)
    vacuum = mr.Scene(mc.twin_spec(spec), mesh)
    rng = np.random.default_rng(7)
    ic = (np.array([-0.3, 0.1, 1.5]), mr.random_quat(rng), np.array([2.5, -3.5, 0.4]),
          np.array([4.0, -15.0, 8.0]))  # spinning fast, so a wrong lift would show
    times = np.arange(46) / 60.0
    pos = np.array([scene.pose_cam(q)[1] for q in scene.simulate(ic, times)])
    pos_vac = np.array([vacuum.pose_cam(q)[1] for q in vacuum.simulate(ic, times)])

    effects = mr.hidden_effects(spec, scene, mesh)
    expected = {"drag_ball": {"quadratic_drag"}, "drag_tshape": {"quadratic_drag"},
                "magnus_tshape": {"magnus"}}[name]
    assert set(effects) == expected
    mesh.export(tmp_path / "mesh.obj")
    shape = load_shape(tmp_path / "mesh.obj", density=spec.density)
    assert shape.mass == pytest.approx(scene.mass, rel=1e-6)
    modules = [make_effect(k, area=shape.reference_area, **v) for k, v in effects.items()]
    state0 = torch.tensor(np.concatenate(ic), dtype=torch.float64)[None]
    gravity = torch.tensor(9.81 * mr.gravity_dir(spec.tilt_deg, spec.roll_deg))
    body = RigidBody.from_shape(shape, torch.float64)
    with torch.no_grad():
        ours = integrate(state0, torch.tensor(times), body, gravity, modules,
                         step_size=1 / 2000).position[0].numpy()
    effect = np.abs(pos - pos_vac).max()
    assert effect > 0.01  # the fluid moves the body by centimetres over 0.75 s
    assert np.abs(pos - ours).max() < 1e-4 * effect
    # and a coefficient 10 % off is 1e3 times worse than the derived one: the check can fail
    wrong = [make_effect(k, area=shape.reference_area, **{p: 1.1 * v for p, v in d.items()})
             for k, d in effects.items()]
    with torch.no_grad():
        off = integrate(state0, torch.tensor(times), body, gravity, wrong,
                        step_size=1 / 2000).position[0].numpy()
    assert np.abs(pos - off).max() > 0.05 * effect


def test_coefficients_formula(mods):
    """C_d = 2 C_blunt, C_L = 8/3 (C_M - 1/2) for MuJoCo's sphere (added mass = half its volume)."""
    mr, mc = mods
    spec = mr.RecordingSpec(name="x", shape="sphere", **mc.drag(0.3))
    mesh = mr.make_mesh("sphere", spec.ball_radius)
    fl = mr.fluid_truth(spec, mr.Scene(spec, mesh), mesh)
    assert fl["drag_coefficient"] == pytest.approx(0.6)
    assert fl["added_mass_volume_m3"] == pytest.approx(fl["volume_m3"] / 2, rel=1e-4)
    spec = spec.replace(**mc.lift(1.25))
    fl = mr.fluid_truth(spec, mr.Scene(spec, mesh), mesh)
    assert fl["lift_coefficient"] == pytest.approx(8 / 3 * 0.75, rel=1e-4)
    assert fl["drag_coefficient"] == 0.0


def test_every_effect_has_two_recordings_and_four_controls(mods):
    _, mc = mods
    hides = {}
    for spec, _ in mc.concealed_specs():
        kinds = [k for k in ("fluid", "hidden_weight", "fps_stated", "distortion")
                 if getattr(spec, k) not in (None, False)]
        assert len(kinds) <= 1, spec.name
        hides.setdefault(kinds[0] if kinds else "none", []).append(spec.name)
    assert len(hides["none"]) >= 4
    for k in ("hidden_weight", "fps_stated", "distortion"):
        assert len(hides[k]) >= 2, k
    names = hides["fluid"]
    assert sum(n.startswith("drag") for n in names) >= 2
    assert sum(n.startswith("magnus") for n in names) >= 2


def test_light_drag_recordings_are_the_heavy_throws_with_a_quarter_of_the_mass(mods):
    """drag_light_* are specified from drag_ball's / drag_box's detection limit: same throw and
    drag, 1/4 of the mass (so 4x the drag's deceleration)."""
    _, mc = mods
    specs = {s.name: s for s, _ in mc.concealed_specs()}
    for heavy in ("drag_ball", "drag_box"):
        light = specs[heavy.replace("drag_", "drag_light_")]
        assert light.replace(density=specs[heavy].density, name=heavy) == specs[heavy]
        assert light.density == pytest.approx(specs[heavy].density / 4, rel=0.01)


def test_fresh_set_changes_only_the_seeds_and_the_scene(mods):
    """--fresh K: the same recipes with other throws (seed + 1000 K) over background scene K."""
    _, mc = mods
    first, fresh = mc.concealed_specs(), mc.concealed_specs(2)
    assert [s.name for s, _ in first] == [s.name for s, _ in fresh]
    for (a, what_a), (b, what_b) in zip(first, fresh):
        assert (b.seed, b.scene_seed, what_b) == (a.seed + 2000, 2, what_a)
        assert b.replace(seed=a.seed, scene_seed=a.scene_seed) == a
    assert mc.fresh_folder(0).name == "recordings" and mc.fresh_folder(2).name == "recordings_fresh2"


def test_sharp_set_changes_only_the_motion_blur(mods):
    """--sharp: the same recordings with one render per frame, at the frame's time, in their own folder."""
    mr, mc = mods
    for spec, _ in mc.concealed_specs(1):
        sharp = mc.sharp_spec(spec)
        assert spec.blur_subframes > 1 and sharp.blur_subframes == 1
        assert sharp.replace(blur_subframes=spec.blur_subframes) == spec
        times, subframes = mr.sample_times(sharp)
        assert np.array_equal(subframes[:, 0], times)
    assert mc.fresh_folder(0, sharp=True).name == "recordings_sharp"
    assert mc.fresh_folder(2, sharp=True).name == "recordings_fresh2_sharp"


def test_plain_set_changes_only_the_scene(mods):
    """--plain: the same throws in front of a wall and a floor of one colour each with their fine
    grain alone (no panels, no tiles), and no cabinet or crate, in their own folder."""
    mr, mc = mods
    spec = next(s for s, _ in mc.concealed_specs(3) if s.name == "control_box")
    plain = spec.replace(plain_scene=True)
    assert plain.replace(plain_scene=False) == spec
    mesh = mr.make_mesh(spec.shape, spec.ball_radius)
    rotation = mr.camera_rotation(spec.tilt_deg, spec.roll_deg)
    assert '<geom name="cabinet"' in mr.build_model_xml(spec, mesh, rotation)[0]
    assert '<geom name="crate"' in mr.build_model_xml(spec, mesh, rotation)[0]
    assert "cabinet" not in mr.build_model_xml(plain, mesh, rotation)[0].split("<worldbody>")[1]
    textured = mr._textures(3)
    flat = mr._textures(3, plain=True)
    decoded = {k: cv2.imdecode(np.frombuffer(v, np.uint8), cv2.IMREAD_COLOR).astype(float) for k, v in flat.items()}
    before = {k: cv2.imdecode(np.frombuffer(v, np.uint8), cv2.IMREAD_COLOR).astype(float) for k, v in textured.items()}
    for name in ("wall.png", "floor.png"):  # grain of 0.015 and 0.02 alone, against panels and tiles
        assert decoded[name].std((0, 1)).max() < 7 < before[name].std((0, 1)).max()
        np.testing.assert_allclose(decoded[name].mean((0, 1)), before[name].mean((0, 1)), atol=3)
    (p, q, v, w), _ = mr.resolve_ic(spec, mr.Scene(spec, mesh), mesh)
    (p2, q2, v2, w2), _ = mr.resolve_ic(plain, mr.Scene(plain, mesh), mesh)
    assert all(np.array_equal(a, b) for a, b in ((p, p2), (q, q2), (v, v2), (w, w2)))
    assert mc.fresh_folder(3, plain=True).name == "recordings_fresh3_plain"


def test_crf_set_folders(mods):
    """--crf C: the set at another H.264 quality, in its own folder beside the set."""
    _, mc = mods
    assert mc.fresh_folder(0, crf=4).name == "recordings_crf4"
    assert mc.fresh_folder(3, crf=20).name == "recordings_fresh3_crf20"


def test_scaled_set_draws_the_same_throws_through_more_pixels(mods):
    """--scale N: the same recordings through a camera with N times the pixels along each side
    (the same field of view), the in-view margin scaled with them, so the same throw is drawn: the
    same orientation and spin, and a position and velocity that differ by the principal point's
    half pixel alone (under a millimetre, a millimetre a second)."""
    mr, mc = mods
    specs = [spec for spec, _ in mc.concealed_specs(7)]
    for spec in specs:
        scaled = mc.scaled_spec(spec, 2)
        assert (scaled.width, scaled.height, scaled.margin_px) == (2 * spec.width, 2 * spec.height, 2 * spec.margin_px)
        assert scaled.replace(width=spec.width, height=spec.height, margin_px=spec.margin_px) == spec
    spec = next(s for s in specs if s.name == "drag_box")
    mesh = mr.make_mesh(spec.shape, spec.ball_radius)
    (p, q, v, w), _ = mr.resolve_ic(spec, mr.Scene(spec, mesh), mesh)
    scaled = mc.scaled_spec(spec, 2)
    (p2, q2, v2, w2), _ = mr.resolve_ic(scaled, mr.Scene(scaled, mesh), mesh)
    assert np.array_equal(q, q2) and np.array_equal(w, w2)
    assert 0 < np.abs(p2 - p).max() < 1e-3 and np.abs(v2 - v).max() < 1e-3
    assert mc.fresh_folder(7, scale=2).name == "recordings_fresh7_x2" and mc.fresh_folder(0, scale=1).name == "recordings"


def test_fps_scaled_set_films_the_same_throws_at_twice_the_frame_rate(mods):
    """--fps-scale N: the same recordings at N times the frame rate over the same seconds, so every
    N-th frame is one of the set's, each exposed for the same fraction of its interval; a wrong
    clock keeps its ratio; the throw is the set's (pinned, where its margin checked at more instants
    would draw another: fresh-6 drag_box), and it stays in the image at every instant."""
    mr, mc = mods
    for spec, _ in mc.concealed_specs(6):
        if spec.name not in ("drag_box", "time_box", "magnus_ball"):  # the pinned one, a clock, a spin
            continue
        fast = mc.fps_scaled_spec(spec, 2)
        assert fast.fps == 2 * spec.fps and fast.n_frames == 2 * spec.n_frames - 1
        assert (fast.n_frames - 1) / fast.fps == pytest.approx((spec.n_frames - 1) / spec.fps)
        assert fast.exposure == spec.exposure and fast.blur_subframes == spec.blur_subframes
        if spec.fps_stated is not None:
            assert fast.fps / fast.fps_stated == pytest.approx(spec.fps / spec.fps_stated)
        mesh = mr.make_mesh(spec.shape, spec.ball_radius)
        ic, _ = mr.resolve_ic(spec, mr.Scene(spec, mesh), mesh)
        ic2, _ = mr.resolve_ic(fast, mr.Scene(fast, mesh), mesh)  # raises if it left the image
        assert all(np.allclose(a, b, rtol=0, atol=1e-15) for a, b in zip(ic, ic2)), spec.name
        unpinned = fast.replace(position=None, orientation_wxyz=None, velocity=None, angular_velocity=None,
                                margin_px=spec.margin_px)
        assert unpinned.replace(fps=spec.fps, n_frames=spec.n_frames, fps_stated=spec.fps_stated) == spec
    assert mc.fps_scaled_spec(spec, 1) is spec
    assert mc.fresh_folder(6, fps_scale=2).name == "recordings_fresh6_fps2"


@pytest.mark.parametrize("factor, fps, subframes, folder", [
    (Fraction(1, 2), 30.0, 9, "recordings_fresh6_fps1by2"),
    (Fraction(5, 6), 50.0, 6, "recordings_fresh6_fps5by6"),
    (Fraction(5, 12), 25.0, 11, "recordings_fresh6_fps5by12")])
def test_fps_scaled_set_below_the_frame_rate_films_the_same_seconds(mods, factor, fps, subframes, folder):
    """--fps-scale 1/2, 5/6, 5/12: the set's throws at 30, 50 and 25 fps over the same seconds
    (the last frame dropped where the new interval does not divide them; at 1/2 every other frame
    of the set's, at 5/6 and 5/12 frames between them), each exposed for the same fraction of its
    interval, so for longer, with sub-frames spaced in time about as the set's (exactly at 1/2);
    a wrong clock keeps its ratio; the same throw, pinned."""
    mr, mc = mods
    for spec, _ in mc.concealed_specs(6):
        if spec.name not in ("time_tshape", "magnus_ball"):  # a clock (45 frames), a spin (54)
            continue
        slow = mc.fps_scaled_spec(spec, factor)
        span = (spec.n_frames - 1) / spec.fps
        assert slow.fps == fps and slow.exposure == spec.exposure and slow.blur_subframes == subframes
        assert span - 1 / slow.fps < (slow.n_frames - 1) / slow.fps <= span
        # the sub-frames' spacing in seconds: the exposure's span over its intervals
        spacing = lambda s: s.exposure / s.fps / (s.blur_subframes - 1)  # noqa: E731
        assert spacing(slow) == pytest.approx(spacing(spec), rel=1e-12 if factor.numerator == 1 else 0.05)
        if spec.fps_stated is not None:
            assert slow.fps / slow.fps_stated == pytest.approx(spec.fps / spec.fps_stated)
        mesh = mr.make_mesh(spec.shape, spec.ball_radius)
        ic, _ = mr.resolve_ic(spec, mr.Scene(spec, mesh), mesh)
        ic2, _ = mr.resolve_ic(slow, mr.Scene(slow, mesh), mesh)
        assert all(np.allclose(a, b, rtol=0, atol=1e-15) for a, b in zip(ic, ic2)), spec.name
    assert mc.fresh_folder(6, fps_scale=factor).name == folder


def test_fps_factor_takes_a_positive_fraction_and_names_a_bad_one(mods):
    """--fps-scale's value: a whole N, 1/N or P/Q above 0; anything else is refused with its value."""
    _, mc = mods
    assert mc.fps_factor("1/2") == Fraction(1, 2) and mc.fps_factor("3") == 3 and mc.fps_factor("5/6") == Fraction(5, 6)
    for bad in ("0", "-2", "-5/6", "x", "1/0"):
        with pytest.raises(ValueError, match=repr(bad)):
            mc.fps_factor(bad)


@pytest.mark.parametrize("codec, full_colour", [("h264_444", True), ("h264", False)])
def test_h264_444_keeps_colour_at_full_resolution(mods, tmp_path, codec, full_colour):
    """A one-pixel red column on grey, lossless (crf 0): yuv444p gives it back, yuv420p halves
    its colour's resolution (what diagnose.py codec separates from the quantisation)."""
    mr, _ = mods
    pytest.importorskip("av")
    import cv2

    frame = np.full((64, 64, 3), 128, np.uint8)
    frame[:, 31] = (200, 40, 40)
    spec = mr.RecordingSpec(name="stripe", codec=codec, crf=0)
    writer = mr.VideoWriter(tmp_path / "v.mp4", spec, 64, 64)
    for _ in range(3):
        writer.write(frame)
    writer.release()
    ok, bgr = cv2.VideoCapture(str(tmp_path / "v.mp4")).read()
    assert ok
    error = np.abs(bgr[:, :, ::-1].astype(int) - frame.astype(int))[8:-8, 28:35].max()
    assert (error <= 3) == full_colour, error


def test_summary_merge_keeps_rows_not_remade(mods):
    _, mc = mods
    kept = [{"name": "control_ball", "v": 1}, {"name": "drag_ball", "v": 1}]
    merged = mc.merge_summary(kept, [{"name": "drag_ball", "v": 2}, {"name": "drag_light_ball", "v": 2}])
    assert merged == [{"name": "drag_ball", "v": 2}, {"name": "drag_light_ball", "v": 2},
                      {"name": "control_ball", "v": 1}]


SMALL = {"width": 320, "height": 240, "n_frames": 20}


@pytest.mark.recordings
@pytest.mark.parametrize("name", ["drag_ball", "magnus_tshape", "com_tshape", "time_box",
                                  "lens_box", "control_cylinder"])
def test_small_recording_truth(mods, tmp_path, name):
    """A 320x240x20 version of each kind: files, effects truth, container fps, hidden geoms kept
    out of the masks, distorted masks matching the distorted mesh, effect size vs its twin."""
    import cv2

    mr, mc = mods
    spec = next(s for s, _ in mc.concealed_specs() if s.name == name).replace(**SMALL)
    if spec.distortion is not None:  # nearest-neighbour remapped masks: ~0.5 px jagged edge,
        spec = spec.replace(min_iou=0.93)  # which costs more IoU at half size (0.95 at 640x480)
    summary = mr.make_recording(spec, tmp_path, verbose=False)
    assert summary["iou_min"] >= spec.min_iou  # distortion: the distorted mesh vs remapped masks
    folder = tmp_path / name
    truth = json.loads((folder / "truth.json").read_text())
    cam = json.loads((folder / "camera.json").read_text())
    assert "dist_coeffs" not in cam
    effects = truth["effects"]
    cap = cv2.VideoCapture(str(folder / "video.mp4"))
    container_fps = cap.get(cv2.CAP_PROP_FPS)
    cap.release()
    size = mc.effect_size(spec, folder)
    if name == "control_cylinder":
        assert effects == {}
        assert size["max_px"] < 0.3
        assert container_fps == pytest.approx(spec.fps, rel=1e-3)
        return
    assert size["max_px"] > 1.0
    if name == "time_box":
        assert container_fps == pytest.approx(60.0, rel=1e-3)
        assert truth["fps_true"] == 58.5 and truth["fps"] == 58.5
        assert effects == {"time_scale": {"time_scale": pytest.approx(58.5 / 60.0)}}
    if name == "com_tshape":
        offset = np.asarray(effects["com_offset"]["offset"])
        assert 0.005 < np.linalg.norm(offset) < 0.015
        np.testing.assert_allclose(np.asarray(truth["object"]["com"]) + offset,
                                   truth["hidden_weight"]["body_com"], atol=1e-12)
        assert truth["object"]["mass"] == pytest.approx(0.189)  # the visible uniform T-handle
    if name == "lens_box":
        assert effects == {"lens_distortion": {"k1": -0.2, "k2": 0.04}}
        assert truth["camera_true"]["dist_coeffs"][:2] == [-0.2, 0.04]
    if name in ("drag_ball", "magnus_tshape"):
        assert set(effects) == {"drag_ball": {"quadratic_drag"},
                                "magnus_tshape": {"magnus"}}[name]


@pytest.mark.recordings
def test_shipped_recording_unchanged(mods, tmp_path):
    """The new spec fields default to the old behaviour: tshape_small's files regenerate
    byte-for-byte (the H.264 stream aside)."""
    mr, _ = mods
    spec = next(s for s in mr.shipped_specs() if s.name == "tshape_small")
    mr.make_recording(spec, tmp_path, verbose=False)
    shipped = ROOT / "torchfit" / "recordings" / "tshape_small"
    for f in ("truth.json", "camera.json", "mesh.obj", "masks.npz"):
        assert (tmp_path / "tshape_small" / f).read_bytes() == (shipped / f).read_bytes(), f


def _content(verdict: list[str], truth: dict) -> dict:
    """A discover.json as concealed.py reads it (two models, round one's scores)."""
    return {"verdict": verdict, "truth_effects": truth, "indistinguishable": [], "seconds": 1.0,
            "located": {"flagged": []}, "iou_baseline": {"mean_fitted": 0.95, "mean_heldout": 0.94},
            "effects": {"quadratic_drag": [{"delta_bic": 20.0, "detectable_above": {"drag_coefficient": 0.3}}],
                        "time_scale": [{"delta_bic": 3.0, "detectable_above": {"time_scale": 0.01},
                                        "unit_delta_chi2": [1.0, 1.0, 6.0]}]},
            "models": [{"heldout_centroid_px": 2.0, "params": {}},
                       {"heldout_centroid_px": 1.0,
                        "params": {"quadratic_drag": {"drag_coefficient": {"value": 0.5, "std": 0.1}}}}]}


def test_concealed_verdict_is_right_only_when_exactly_the_hidden_effects_are_named():
    """A spurious second name makes a verdict wrong, as a wrong first one does; controls must name nothing."""
    sys.path.insert(0, str(CONCEALED.parent))  # concealed.py imports true_masks from its folder
    conc = _load("concealed", CONCEALED.parent / "concealed.py")
    drag = {"quadratic_drag": {"drag_coefficient": 0.5}}
    exact = conc.row("drag_x", _content(["quadratic_drag"], drag))
    extra = conc.row("drag_x", _content(["quadratic_drag", "com_offset"], drag))
    wrong = conc.row("drag_x", _content(["time_scale"], drag))
    quiet = conc.row("control_x", _content([], {}))
    alarm = conc.row("control_x", _content(["time_scale"], {}))
    assert [r["right"] for r in (exact, extra, wrong, quiet, alarm)] == [True, False, False, True, False]
    assert exact["top_delta_bic"] == ["quadratic_drag", 20.0, None]
    score = _content([], {})["effects"]["time_scale"][0]
    assert conc._without_third(score) == pytest.approx(-3.0)  # 3.0 without the last frame's 6.0
    score["delta_bic_without_block"] = 2.5  # a run with the rule stored it: taken as it is
    assert conc._without_third(score) == 2.5
    table = conc.table([exact, extra, wrong])
    assert "| NO (also named com_offset) |" in table and table.count("| NO |") == 1
    wrong["concealed"] = False  # its baseline fitted at IoU < 0.9
    counts = conc.score([exact, extra, wrong, quiet, alarm])
    assert counts["concealed"] == [2, 3]  # effect cases only: a control has nothing to conceal
    assert counts["effect_right"] == [1, 3] and counts["controls_quiet"] == [1, 2]
    assert counts["wrong_names"] == ["control_x", "drag_x", "drag_x"]
    assert counts["heldout_halved"] == [1, 1]  # 2.0 -> 1.0 px
    assert counts["coefficients_within_25pc"] == [1, 1]  # C_d 0.5 fitted, 0.5 true
    assert "Right verdict on 1 of 3 effect cases; controls quiet 1 of 2" in conc.score_line(counts)


def test_table_rebuild_keeps_a_stored_row_whose_recording_is_gone(tmp_path):
    """A set partly made again: a centre-of-mass run whose recording is gone keeps the row
    summary.json holds for it (its offset was compared modulo the shape when it was there); every
    other row is read again from its discover.json, and without a stored row the rebuild stops,
    naming the recording."""
    sys.path.insert(0, str(CONCEALED.parent))
    conc = _load("concealed", CONCEALED.parent / "concealed.py")
    out, recordings = tmp_path / "out", tmp_path / "recordings"
    recordings.mkdir()
    com = {"com_offset": {"offset": [0.0, 0.0, 0.01]}}
    for name, verdict, truth in (("com_x", ["com_offset"], com), ("control_x", [], {})):
        (out / name).mkdir(parents=True)
        (out / name / "discover.json").write_text(json.dumps(_content(verdict, truth)))
    with pytest.raises(SystemExit, match="com_x is missing"):
        conc.rebuild(out, recordings)
    stored = conc.row("com_x", _content(["com_offset"], {})) | {"marker": "stored"}  # a whole row, marked
    (out / "summary.json").write_text(json.dumps([stored]))
    conc.rebuild(out, recordings)
    rows = {r["recording"]: r for r in json.loads((out / "summary.json").read_text())}
    assert rows["com_x"] == stored
    assert rows["control_x"]["right"] and "marker" not in rows["control_x"]


def test_below_the_exact_mask_limit_only_when_missed_and_every_limit_exceeds_the_truth():
    """A recording counts as below its exact-mask detection limit only when the exact masks miss
    it and each parameter's limit there is larger than its true departure from the null."""
    sys.path.insert(0, str(CONCEALED.parent))
    conc = _load("concealed", CONCEALED.parent / "concealed.py")
    weak = {"quadratic_drag": {"drag_coefficient": 0.2}}  # limit 0.3 in _content
    strong = {"quadratic_drag": {"drag_coefficient": 0.5}}
    assert conc.below_limit(conc.row("drag_x", _content([], weak)))
    assert not conc.below_limit(conc.row("drag_x", _content([], strong)))  # missed, yet above its limit
    assert not conc.below_limit(conc.row("drag_x", _content(["quadratic_drag"], weak)))  # named
    assert not conc.below_limit(conc.row("control_x", _content([], {})))
    clock = conc.row("time_x", _content([], {"time_scale": {"time_scale": 1.005}}))  # limit 0.01 on 0.005
    assert conc.below_limit(clock)
    lens = _content([], {"lens_distortion": {"k1": -0.05, "k2": 0.01}})
    lens["effects"]["lens_distortion"] = [{"delta_bic": 1.0, "detectable_above": {"k1": 0.2, "k2": 0.5}}]
    assert not conc.below_limit(conc.row("lens_x", lens))  # two numbers: never called below


def test_a_named_lens_is_compared_by_its_shift_where_the_object_went():
    """A named lens is compared with the engine's by the shift each gives the point seen farthest
    out (the run's ``lens_shift``, at its radius and focal length), beside k1 and k2; the shift is
    no drag or lift, so the coefficients' count leaves it out, and coefficients.py lists it."""
    sys.path.insert(0, str(CONCEALED.parent))
    conc = _load("concealed", CONCEALED.parent / "concealed.py")
    coefficients = _load("coefficients", CONCEALED.parent / "coefficients.py")
    truth = {"lens_distortion": {"k1": -0.2, "k2": 0.04}}
    content = _content(["lens_distortion"], truth)
    content["models"][-1]["params"] = {"lens_distortion": {"k1": {"value": -0.05, "std": 0.03},
                                                           "k2": {"value": -0.5, "std": 0.1}}}
    # the engine's lens at 0.5 normalised units (300 px at 600 px): rho_u solves
    # rho (1 - 0.2 rho^2 + 0.04 rho^4) = 0.5, 0.527762..., a shift of 600 (0.5 - rho_u) = -16.66 px
    content["models"][-1]["lens_shift"] = {"radius_px": 300.0, "focal_px": 600.0, "value_px": -15.0,
                                           "std_px": 1.0, "correlation": -0.97}
    r = conc.row("lens_box", content)
    shift = r["params"]["lens_distortion"]["shift_px"]
    assert shift["fitted"] == -15.0 and shift["std"] == 1.0
    assert shift["true"] == pytest.approx(-16.6572, abs=1e-3)
    assert conc.score([r])["coefficients_within_25pc"] == [0, 0]
    assert "shift_px -15 ± 1 (true -16.7)" in conc.table([r])
    rows = coefficients.coefficient_rows(content)
    assert rows[-1] == ("lens_distortion", "shift_px", pytest.approx(-16.6572, abs=1e-3), -15.0, 1.0)


def test_a_balls_lift_is_compared_across_the_direction_the_video_sees_least():
    """A ball's named lift is compared with the engine's as the video measures it: the size of
    ``C_L ω``'s part across the direction the run's covariance knows least (both vectors across
    that same direction), within 25 % counted as a coefficient, the angle beside it; the part
    across each side's own initial velocity (the count before the thirty-sixth session) is kept
    beside it. Its round-one limit (a C_L that trades with the spin) gives no limit ratio;
    coefficients.py reads the same number and leaves the ball's C_L out."""
    sys.path.insert(0, str(CONCEALED.parent))
    conc = _load("concealed", CONCEALED.parent / "concealed.py")
    coefficients = _load("coefficients", CONCEALED.parent / "coefficients.py")
    truth = {"magnus": {"lift_coefficient": 2.0}}
    content = _content(["magnus"], truth)
    content["truth_motion"] = {"shape": "sphere", "velocity": [0.0, 0.0, 2.0], "angular_velocity": [0.0, -1.5, 2.0]}
    content["effects"]["magnus"] = [{"delta_bic": 50.0, "detectable_above": {"lift_coefficient": 0.1}}]
    content["models"][-1]["params"] = {"magnus": {"lift_coefficient": {"value": -0.3, "std": 9.0}}}
    # fitted (2, -2, 7), known least along x (90° from the velocity, z): across x (0, -2, 7), size
    # √53, std √(53 · 0.04) / √53 = 0.2; the truth's (0, -3, 4) across x: 5, 20.9° from it
    content["models"][-1]["ball_lift"] = {"value": [2.0, -2.0, 7.0], "velocity": [0.0, 0.0, 1.0],
                                          "covariance": [[1.0, 0, 0], [0, 0.04, 0], [0, 0, 0.04]]}
    r = conc.row("magnus_ball", content)
    lift = r["params"]["magnus"]["lift_across"]
    assert lift["fitted"] == pytest.approx(53 ** 0.5) and lift["true"] == pytest.approx(5.0)
    assert lift["std"] == pytest.approx(0.2) and lift["angle_deg"] == pytest.approx(20.925, abs=1e-3)
    assert lift["direction_deg"] == pytest.approx(90.0)
    # across each initial velocity (z): (2, -2, 0) against (0, -3, 0), 45° apart
    assert lift["across_velocity"] == {"fitted": pytest.approx(8 ** 0.5), "std": pytest.approx((4.16 / 8) ** 0.5),
                                       "true": pytest.approx(3.0), "angle_deg": pytest.approx(45.0)}
    assert conc.score([r])["coefficients_within_25pc"] == [0, 1]  # 7.28 against 5
    assert conc.limit_ratio(r) is None and r["spin_hidden"]
    assert coefficients.coefficient_rows(content) == [("magnus", "lift_across", 5.0, pytest.approx(53 ** 0.5),
                                                      pytest.approx(0.2))]
    assert coefficients.unselected_rows(content) == []
    # a spinning body that shows its spin keeps its C_L, its limit and its ratio
    content["truth_motion"]["shape"] = "tshape"
    del content["models"][-1]["ball_lift"]
    r = conc.row("magnus_tshape", content)
    assert list(r["params"]["magnus"]) == ["lift_coefficient"] and conc.limit_ratio(r) == pytest.approx(20.0)
    assert coefficients.coefficient_rows(content)[0][:2] == ("magnus", "lift_coefficient")


def test_standing_checks_the_runs_own_limit_against_what_it_named(tmp_path):
    """standing.py: the truth over the run's limit for a single scalar effect (None for a control
    or a lens), counted per bin with whether the run named exactly the hidden effect (a second
    name counts as not named); the targets table sums the sets."""
    sys.path.insert(0, str(CONCEALED.parent))
    conc = _load("concealed", CONCEALED.parent / "concealed.py")
    standing = _load("standing", CONCEALED.parent / "standing.py")
    drag = lambda cd: {"quadratic_drag": {"drag_coefficient": cd}}  # limit 0.3 in _content
    case = lambda verdict, truth, name="drag_x": standing.cases(conc.row(name, _content(verdict, truth)))
    assert case([], drag(0.12)) == (pytest.approx(0.4), False)
    assert case(["quadratic_drag"], drag(0.6)) == (pytest.approx(2.0), True)
    assert case(["quadratic_drag", "time_scale"], drag(0.6))[1] is False
    assert case([], {}, "control_x") is None
    assert case(["time_scale"], {"time_scale": {"time_scale": 0.985}}, "time_x") == (pytest.approx(1.5), True)
    lens = _content([], {"lens_distortion": {"k1": -0.05, "k2": 0.01}})
    lens["effects"]["lens_distortion"] = [{"delta_bic": 1.0, "detectable_above": {"k1": 0.2, "k2": 0.5}}]
    assert standing.cases(conc.row("lens_x", lens)) is None
    rows = standing.tally([(0.4, False), (0.7, True), (1.0, True), (1.2, False), (2.5, True)])
    assert rows == [("0–0.5", 1, 0), ("0.5–1", 1, 1), ("1–1.5", 2, 1), ("1.5–2", 0, 0), ("≥ 2", 1, 1),
                    ("**below 1**", 2, 1), ("**1 or above**", 3, 2)]
    by_set = {"first": {"drag_a": conc.row("drag_a", _content(["quadratic_drag"], drag(0.6))),
                        "control_x": conc.row("control_x", _content([], {}))},
              "fresh 1": {"drag_a": conc.row("drag_a", _content([], drag(0.12)))}}
    table = standing.targets(by_set).splitlines()
    assert table[2].startswith("| first | 1 of 1 | 1 of 1 | none |")
    assert table[3].startswith("| fresh 1 | 0 of 1 | 0 of 0 | none |")
    assert table[4].startswith("| **all** | 1 of 2 | 1 of 1 | none |")
    assert standing.limits_table(by_set).splitlines()[-1] == "| **1 or above** | 1 | 1 |"
    # where the report located a miss: a named drag whose baseline's predictions miss and its
    # final model's do not; an older run without the predictions' line counted apart
    named = _content(["quadratic_drag"], drag(0.6))
    named["located"] = {"flagged": ["centroid_y"]}
    named["located_heldout"] = [{"flagged": []}, {"flagged": ["centroid_x", "scale"]}]
    named["located_heldout_after"] = [{"flagged": []}, {"flagged": []}]
    assert conc.flagged(named) == {"fit": True, "predicted": True, "predicted_after": False}
    assert conc.flagged(_content([], {})) == {"fit": False, "predicted": None, "predicted_after": None}
    by_set["first"]["drag_a"] = conc.row("drag_a", named)
    table = standing.located_table(by_set).splitlines()
    assert table[2] == "| named right, held-out error halved | 1 | 1 | 1 of 1 | 0 of 1 | 0 |"  # 2 px -> 1 px
    assert table[3] == "| named right, not halved | 0 | 0 | 0 of 0 | 0 of 0 | 0 |"
    assert table[4] == "| effect not named right | 1 | 0 | 0 of 0 | 0 of 0 | 1 |"
    # the baselines' fitted exposure: quartiles over the runs that fitted one, and those at its bound
    assert standing.exposure_line(by_set) == "No run fitted the exposure."
    for value, (label, name) in zip((0.5, 0.6, 1.0), (("first", "drag_a"), ("first", "control_x"), ("fresh 1", "drag_a"))):
        content = _content([], {})
        content["exposure_fitted"] = [{"value": value, "std": 0.01}, {"value": 0.2, "std": 0.01}]  # baseline's first
        by_set[label][name] = conc.row(name, content)
    assert standing.exposure_line(by_set) == (
        "The baselines' fitted exposure (of the frame interval; the recordings' 0.5), 3 runs: median 0.600, "
        "quartiles 0.550–0.800, range 0.500–1.000; at its bound (0.99 or more) on 1: fresh 1 drag_a.")
    content = _content([], {})
    content["outlier_frames"] = [0, 1]
    by_set["first"]["control_x"] = conc.row("control_x", content)
    assert standing.outlier_line(by_set) == "Frames left out as segmentation failures: on 1 of 3 runs, 2 frames in all."
    assert table[5] == "| control | 1 | 0 | 0 of 0 | 0 of 0 | 1 |"
    # two variants of the same set side by side: a drag below its limit (0.12 of 0.3) named where
    # the other's limit is 0.1, a control quiet in both
    sharper = _content(["quadratic_drag"], drag(0.12))
    sharper["effects"]["quadratic_drag"][0]["detectable_above"] = {"drag_coefficient": 0.1}
    first = {"first": {"drag_a": conc.row("drag_a", _content([], drag(0.12))),
                       "control_x": conc.row("control_x", _content([], {}))}}
    second = {"first": {"drag_a": conc.row("drag_a", sharper), "control_x": conc.row("control_x", _content([], {}))}}
    lines = standing.beside(first, second, ("small", "large")).splitlines()
    assert lines[2] == "| first | 1 | 0 | 1 | 1 of 1 | 1 of 1 | drag_a below limit → right |"
    assert lines[3] == "| **all** | 1 | 0 | 1 | 1 | 1 | |"
    assert "large's detection limit is 3.00 times lower than small's" in lines[-1]
    assert "small's detection limit is 3.00 times higher than large's" in standing.beside(
        second, first, ("large", "small")).splitlines()[-1]


def test_outcome_tells_honest_answers_from_failures(tmp_path):
    """Each effect case ends in exactly one of OUTCOMES: named right; a tie reported between
    look-alikes that holds the truth; nothing named where the run's own detection limit is above
    the truth (or not); a verdict withheld; a name not hidden. The table counts them per set."""
    sys.path.insert(0, str(CONCEALED.parent))
    conc = _load("concealed", CONCEALED.parent / "concealed.py")
    weak = {"quadratic_drag": {"drag_coefficient": 0.2}}  # limit 0.3 in _content
    strong = {"quadratic_drag": {"drag_coefficient": 0.5}}
    tie = _content([], strong) | {"indistinguishable": [["time_scale", "quadratic_drag"]]}
    other_tie = _content([], strong) | {"indistinguishable": [["time_scale", "lens_distortion"]]}
    withheld = _content([], strong) | {"verdict_withheld": ["quadratic_drag"]}
    lens = _content([], {"lens_distortion": {"k1": -0.2, "k2": 0.04}})  # two numbers: no scalar limit
    cases = {"named": _content(["quadratic_drag"], strong), "tie": tie, "below": _content([], weak),
             "above": _content([], strong), "other_tie": other_tie, "withheld": withheld,
             "wrong": _content(["quadratic_drag", "time_scale"], strong), "lens": lens}
    ended = {name: conc.outcome(conc.row(f"drag_{name}", content)) for name, content in cases.items()}
    assert ended == {"named": conc.OUTCOMES[0], "tie": conc.OUTCOMES[1], "below": conc.OUTCOMES[2],
                     "above": conc.OUTCOMES[3], "other_tie": conc.OUTCOMES[3], "withheld": conc.OUTCOMES[4],
                     "wrong": conc.OUTCOMES[5], "lens": conc.OUTCOMES[3]}
    assert "above" not in conc.OUTCOMES[3]  # the lens's miss has no limit to be above
    assert conc.outcome(conc.row("control_x", _content(["time_scale"], {}))) == conc.OUTCOMES[5]
    rows = [conc.row(f"drag_{name}", content) for name, content in cases.items()]
    rows.append(conc.row("control_x", _content([], {})))  # controls are not effect cases
    (tmp_path / "concealed").mkdir()
    (tmp_path / "concealed" / "summary.json").write_text(json.dumps(rows))
    table = conc.outcomes(tmp_path)
    assert "| first | 1 | 1 (drag_tie) | 1 (drag_below) | 3 (drag_above, drag_other_tie, drag_lens) " \
           "| 1 (drag_withheld) | 1 (drag_wrong) |" in table
    assert table.splitlines()[-1] == "| **all** | **1** | **1** | **1** | **3** | **1** | **1** |"
    grid = conc.verdict_grid(tmp_path).splitlines()
    assert grid[0] == "| recording | hidden | first |"
    assert "| drag_named | quadratic_drag | right |" in grid and "| drag_below | quadratic_drag | below limit |" in grid
    assert "| drag_tie | quadratic_drag | tie: time_scale, quadratic_drag |" in grid
    assert "| drag_withheld | quadratic_drag | WITHHELD: quadratic_drag |" in grid
    assert "| drag_wrong | quadratic_drag | WRONG: quadratic_drag, time_scale |" in grid
    assert grid[-1] == "| control_x | nothing | quiet |"  # controls last


def test_scoreboard_takes_the_exact_limit_from_the_exact_masks_own_floor_where_run(tmp_path):
    """A weak drag missed on the exact masks at the segmentation's floor (its limit above the
    truth) is below the exact-mask limit, unless its run at the exact masks' own floor
    (EXACT_EDGE_PX) names it; the scoreboard has a row for each kind of masks."""
    sys.path.insert(0, str(CONCEALED.parent))
    conc = _load("concealed", CONCEALED.parent / "concealed.py")
    weak = {"quadratic_drag": {"drag_coefficient": 0.2}}  # limit 0.3 in _content
    runs = {"concealed": {"drag_a": [], "drag_b": [], "control_x": []},
            "concealed_true_masks": {"drag_a": [], "drag_b": [], "control_x": []},
            f"concealed_true_masks_edge{conc.EXACT_EDGE_PX:g}": {"drag_a": ["quadratic_drag"], "control_x": []}}
    for name, verdicts in runs.items():
        rows = [conc.row(rec, _content(verdict, {} if rec.startswith("control") else weak))
                for rec, verdict in verdicts.items()]
        (tmp_path / name).mkdir()
        (tmp_path / name / "summary.json").write_text(json.dumps(rows))
    board = conc.scoreboard(tmp_path)
    assert "| first | below the exact-mask limit | drag_b |" in board  # drag_a is named at the own floor
    assert "| first | segmented | 0 of 2 | 1 of 1 | none | 0 of 0 | 0 of 0 | 2 of 2 | 0 of 1 |" in board
    assert "| first | exact | 0 of 2 | 1 of 1 | none | 0 of 0 | 0 of 0 | 2 of 2 | 0 of 1 |" in board
    floor = f"exact, floor {conc.EXACT_EDGE_PX:g} px"
    assert f"| first | {floor} | 1 of 1 | 1 of 1 | none | 1 of 1 | 0 of 1 | 1 of 1 | 1 of 1 |" in board  # C_d 0.5 on 0.2
    assert f"| **all** | {floor} | 1 of 1 |" in board


def test_rule_tally_counts_only_what_one_test_alone_kept_out_of_its_round(tmp_path):
    """A candidate counts against a test when it fails that test only and would have changed its
    round: nothing passed there, or its ΔBIC is within the look-alike margin of the winner's or
    above it. Right when its effect is the hidden one."""
    sys.path.insert(0, str(CONCEALED.parent))
    conc = _load("concealed", CONCEALED.parent / "concealed.py")

    def cand(base, dbic, fails):
        return {"base": base, "delta_bic": dbic, "fails": fails, "passes": not fails}

    runs = {
        # the hidden drag kept out by the held-out test alone, nothing passed: right, counted
        "drag_a": ({"quadratic_drag": {}}, {"quadratic_drag": [cand([], 23.7, ["heldout"])],
                                            "time_scale": [cand([], 18.0, ["heldout", "wald"])]}),
        # a clock kept out by Wald alone, 5 below the passing drag's ΔBIC: wrong, counted
        "drag_b": ({"quadratic_drag": {}}, {"quadratic_drag": [cand([], 30.0, [])],
                                            "time_scale": [cand([], 25.0, ["wald"]),
                                                           cand(["quadratic_drag"], 4.0, ["delta_bic", "wald"])]}),
        # a second-round offset 30 below that round's winner: not counted
        "drag_c": ({"quadratic_drag": {}}, {"quadratic_drag": [cand([], 60.0, [])],
                                            "com_offset": [cand([], 30.0, ["evidence_spread"])]}),
    }
    for name, (truth, effects) in runs.items():
        (tmp_path / "concealed" / name).mkdir(parents=True)
        content = {"truth_effects": truth, "effects": effects}
        (tmp_path / "concealed" / name / "discover.json").write_text(json.dumps(content))
    tally = conc.rule_tally(tmp_path)
    seg = tally["segmented"]
    assert seg["heldout"] == {"right": ["first/drag_a: quadratic_drag ΔBIC 23.7"], "wrong": []}
    assert seg["wald"] == {"right": [], "wrong": ["first/drag_b: time_scale ΔBIC 25.0"]}
    assert seg["evidence_spread"] == {"right": [], "wrong": []}
    assert all(kept == {"right": [], "wrong": []} for kept in tally["exact"].values())
    assert "| segmented | heldout | 1: first/drag_a: quadratic_drag ΔBIC 23.7 | 0 |" in conc.rules_text(tally)
    # a variant's runs (its folders' suffix) in place of the default kinds of masks
    (tmp_path / "concealed_albedo1").mkdir()
    (tmp_path / "concealed" / "drag_a").rename(tmp_path / "concealed_albedo1" / "drag_a")
    variant = conc.rule_tally(tmp_path, {"albedo": "_albedo1"})
    assert list(variant) == ["albedo"]
    assert variant["albedo"]["heldout"] == {"right": ["first/drag_a: quadratic_drag ΔBIC 23.7"], "wrong": []}
    assert variant["albedo"]["wald"] == {"right": [], "wrong": []}


def test_round_gains_names_each_candidate_by_the_round_it_was_scored_in():
    """--compare's held-out listing keys every candidate score by its round (the effects it adds
    to) and gives the held-out gain in per cent."""
    sys.path.insert(0, str(CONCEALED.parent))
    conc = _load("concealed", CONCEALED.parent / "concealed.py")
    content = {"effects": {"magnus": [{"base": [], "delta_bic": 3.0, "heldout_gain": -0.5},
                                      {"base": ["quadratic_drag"], "delta_bic": 11.8, "heldout_gain": 0.25}]}}
    assert conc._round_gains(content) == {("baseline", "magnus"): (3.0, -50.0),
                                          ("quadratic_drag", "magnus"): (11.8, 25.0)}


@pytest.mark.parametrize("suffix, kind", [("_chroma0.75", "segmented"), ("_with_rolling_shutter", "exact"),
                                          ("_edge0.03", "exact")])
def test_side_by_side_counts_only_recordings_run_both_ways(tmp_path, suffix, kind):
    """A variant's comparison (another chroma weight, one more candidate) scores each way over the
    recordings run both ways, and lists every recording whose verdict changed."""
    sys.path.insert(0, str(CONCEALED.parent))
    conc = _load("concealed", CONCEALED.parent / "concealed.py")
    drag = {"quadratic_drag": {"drag_coefficient": 0.5}}
    folder = "concealed" + ("_true_masks" if kind == "exact" else "")
    runs = {folder: {"drag_a": ["quadratic_drag"], "drag_b": [], "control_x": [], "drag_only_here": []},
            folder + suffix: {"drag_a": [], "drag_b": ["quadratic_drag"], "control_x": []}}
    for name, verdicts in runs.items():
        rows = [conc.row(rec, _content(verdict, {} if rec.startswith("control") else drag))
                for rec, verdict in verdicts.items()]
        (tmp_path / name).mkdir()
        (tmp_path / name / "summary.json").write_text(json.dumps(rows))
    text = conc.side_by_side(suffix, "variant", tmp_path, masks=("segmented", "exact"))
    for variant in ("default", "variant"):
        assert f"| first | {kind} | {variant} | 1 of 2 | 1 of 1 | none | 1 of 1 | 1 of 1 | 3 |" in text
        assert f"| **all** | {kind} | {variant} | 1 of 2 | 1 of 1 | none | 1 of 1 | 1 of 1 | 3 |" in text
    assert f"| first | {kind} | drag_a | quadratic_drag | quadratic_drag (yes) | none (NO) | 1.00 / 1.00 |" in text
    assert f"| first | {kind} | drag_b | quadratic_drag | none (NO) | quadratic_drag (yes) | 1.00 / 1.00 |" in text
    assert "drag_only_here" not in text and "control_x" not in text.split("differs")[1]
    other = "exact" if kind == "segmented" else "segmented"
    assert f"| first | {other} |" not in text  # no set of the other masks was run both ways


def test_side_by_side_compares_a_variant_with_the_path_it_extends(tmp_path):
    """With ``base``, a variant layered on another path (the speed-scaled floors on the exposure
    path) is compared with that path's runs, named ``base_label``, not with the default's."""
    sys.path.insert(0, str(CONCEALED.parent))
    conc = _load("concealed", CONCEALED.parent / "concealed.py")
    drag = {"quadratic_drag": {"drag_coefficient": 0.5}}
    runs = {"concealed": {"drag_a": [], "drag_b": []},
            "concealed_path": {"drag_a": ["quadratic_drag"], "drag_b": []},
            "concealed_path_more": {"drag_a": ["quadratic_drag"], "drag_b": ["quadratic_drag"]}}
    for name, verdicts in runs.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "summary.json").write_text(
            json.dumps([conc.row(rec, _content(verdict, drag)) for rec, verdict in verdicts.items()]))
    text = conc.side_by_side("_path_more", "more", tmp_path, base="_path", base_label="path")
    assert "| first | segmented | path | 1 of 2 |" in text and "| first | segmented | more | 2 of 2 |" in text
    assert "| first | segmented | drag_b | quadratic_drag | none (NO) | quadratic_drag (yes) | 1.00 / 1.00 |" in text
    assert "drag_a" not in text.split("differs")[1] and "default" not in text


def test_candidate_rounds_lists_the_rounds_an_extra_candidate_beat_the_threshold(tmp_path):
    """--scoreboard --with NAME lists each round where NAME lowered the BIC by more than the
    threshold, with the tests it failed and the round's strongest passing candidate."""
    sys.path.insert(0, str(CONCEALED.parent))
    conc = _load("concealed", CONCEALED.parent / "concealed.py")

    def sc(base, bic, fails=()):
        return {"base": base, "delta_bic": bic, "fails": list(fails), "passes": not fails}

    content = {"truth_effects": {"com_offset": {}}, "verdict": ["com_offset"],
               "effects": {"com_offset": [sc([], 300.0)],
                           "rolling_shutter": [sc([], 80.0), sc(["com_offset"], 12.0, ["evidence_spread"])],
                           "magnus": [sc([], 15.0, ["heldout"]), sc(["com_offset"], 2.0, ["delta_bic"])]}}
    quiet = {"truth_effects": {}, "verdict": [], "effects": {"rolling_shutter": [sc([], 4.0, ["delta_bic"])]}}
    for folder, name, body in (("concealed_with_rolling_shutter", "com_box", content),
                               ("concealed_fresh2_true_masks_with_rolling_shutter", "control_box", quiet)):
        (tmp_path / folder / name).mkdir(parents=True)
        (tmp_path / folder / name / "discover.json").write_text(json.dumps(body))
    lines = conc.candidate_rounds("rolling_shutter", tmp_path).splitlines()
    assert lines[2:] == [
        "| first | segmented | com_box | com_offset | baseline | 80.0 | none | com_offset 300.0 | com_offset |",
        "| first | segmented | com_box | com_offset | com_offset | 12.0 | evidence_spread | none | com_offset |"]


def test_shutter_set_is_the_controls_throws_through_a_rolling_shutter(mods):
    """make_concealed.py --shutter: the four controls' specs with a shutter (30 µs/row for the
    T-handle and the box, 20 for the cylinder and the ball; so the same flights), whose twin has none; the bands tile the rows, each offset is
    the delay at its centre row, and every band time of every frame and blur sub-frame is sampled."""
    mr, mc = mods
    specs = {s.name: s for s, _ in mc.shutter_specs()}
    controls = {s.name: s for s, _ in mc.concealed_specs(0)}
    shapes = {"tshape": 3e-5, "box": 3e-5, "cylinder": 2e-5, "ball": 2e-5}
    assert sorted(specs) == sorted(f"{kind}_{shape}" for shape in shapes for kind in ("control", "shutter"))
    for shape, delay in shapes.items():
        name = f"shutter_{shape}"
        assert specs[name] == controls[f"control_{shape}"].replace(name=name, line_delay=delay)
        assert specs[f"control_{shape}"] == controls[f"control_{shape}"]
        assert mc.twin_spec(specs[name]).line_delay is None
    bands = mr.shutter_bands(specs["shutter_tshape"])
    assert bands[0][0] == 0 and bands[-1][1] == 480 and all(b[1] == n[0] for b, n in zip(bands, bands[1:]))
    for first, end, offset in bands:
        assert offset == pytest.approx(3e-5 * ((first + end - 1) / 2 - 239.5), abs=1e-15)
    assert mr.shutter_bands(controls["control_tshape"]) == []
    times = set(mr.all_times(specs["shutter_tshape"]).tolist())
    tf, ts = mr.sample_times(specs["shutter_tshape"])
    assert {float(ts[3, 0] + bands[7][2]), float(tf[5] + bands[-1][2]), float(tf[0])} <= times


def test_recording_exposure_takes_a_guessed_fraction_and_keeps_the_sub_frames():
    """``concealed.py --exposure --exposure-fraction F``: the recording's own sub-frame count with F
    in place of its exposure, in a results folder of its own; without F the recording's own."""
    sys.path.insert(0, str(CONCEALED.parent))
    conc = _load("concealed", CONCEALED.parent / "concealed.py")
    truth = {"render": {"blur_subframes": 5, "exposure_frac": 0.5}}
    own, guess = conc.recording_exposure(truth), conc.recording_exposure(truth, 0.25)
    assert (own.fraction, own.taps) == (0.5, 5)
    assert (guess.fraction, guess.taps) == (0.25, 5)
    assert conc.recording_exposure({"render": {"blur_subframes": 1, "exposure_frac": 0.5}}).fraction == 0.0
    assert (conc.exposure_suffix(None), conc.exposure_suffix(0.25)) == ("_exposure", "_exposure0.25")
    assert conc.segmentation_suffix(1, True, None, 8, False) == "_albedo1_exposure_near8_unclipped"
    assert conc.segmentation_suffix(1, True, None, None, None) == "_albedo1_exposure"
    assert conc.segmentation_suffix(1, True, None, None, None, False, (0.0, math.inf)) == "_albedo1_exposure_spread"
    assert (conc.segmentation_suffix(1, True, 0.25, None, None, True, (1.0, 0.5))
            == "_albedo1_exposure0.25_fitted_spread1pm0.5")
    camera = conc.recording_exposure(truth, 0.5, taps=0)  # --exposure-taps 0: as a camera's
    assert (camera.fraction, camera.taps) == (0.5, 0)
    assert conc.segmentation_suffix(1, True, 0.5, None, None, True, exposure_taps=0) == "_albedo1_exposure0.5_taps0_fitted"
    assert (conc.segmentation_suffix(1, True, 0.5, None, None, True, exposure_taps=0, well_posed_grey=5.0)
            == "_albedo1_exposure0.5_taps0_fitted_grey5")


def test_results_folders_carry_their_settings_on_every_set():
    """Each set's runs go to a folder named after the set, the masks and the settings: the
    rolling-shutter set's too (its runs on the masks, before settings had names, keep
    ``rolling_shutter``), so a rerun on other settings never overwrites the stored one."""
    sys.path.insert(0, str(CONCEALED.parent))
    conc = _load("concealed", CONCEALED.parent / "concealed.py")
    default = (conc.segmentation_suffix(1, True, 0.5, None, None, True, exposure_taps=0)
               + conc.robust_suffix(2.0) + conc.backcast_suffix(True))
    assert conc.results_name(default, shutter=True) == "rolling_shutter_albedo1_exposure0.5_taps0_fitted_huber2_backcast"
    assert conc.results_name("", shutter=True) == "rolling_shutter"
    assert conc.results_name("", shutter=True, true_masks=True) == "rolling_shutter_true_masks"
    assert (conc.results_name(default, fresh=3)
            == "concealed_fresh3_albedo1_exposure0.5_taps0_fitted_huber2_backcast")
    assert conc.results_name("_with_rolling_shutter", true_masks=True) == "concealed_true_masks_with_rolling_shutter"
    assert conc.results_name(default, fresh=2, variant="_sharp") == (
        "concealed_fresh2_albedo1_exposure0.5_taps0_fitted_huber2_backcast_sharp")
    assert conc.results_name(default, shipped=True) == "shipped"
    assert conc.results_name(default + conc.final_suffix(12), fresh=4) == (
        "concealed_fresh4_albedo1_exposure0.5_taps0_fitted_huber2_backcast_final12")
    assert conc.final_suffix(6) == ""  # the first runs' search: their folders keep their names
    assert conc.final_suffix(None) == conc.final_suffix(SearchSettings().final) == "_final12"
    assert conc.results_name(default + conc.final_suffix(12) + conc.jump_suffix(None), fresh=6) == (
        "concealed_fresh6_albedo1_exposure0.5_taps0_fitted_huber2_backcast_final12_nojump")
    assert conc.jump_suffix(conc.JUMP_SIGMAS) == ""  # the jump test at its default: the default's folders
    assert conc.jump_suffix(4.0) == "_jump4"
    assert conc.jump_suffix(conc.JUMP_SIGMAS, True) == "_1by1" and conc.jump_suffix(4.0, True) == "_jump4_1by1"
    assert conc.jump_suffix(conc.JUMP_SIGMAS, False, 1) == "_nb1" and conc.jump_suffix(4.0, True, 2) == "_jump4_1by1_nb2"
    assert conc.jump_suffix(conc.JUMP_SIGMAS, refined=True) == "_refj"


def test_blur_estimates_recover_a_known_exposure():
    """``diagnose.py blur-estimate``'s two pieces on synthetic answers: the ramp width of a ramp
    alone is its length and of a Gaussian alone ``6 sigma / sqrt(pi)``; the along-motion
    variance of a blurred silhouette over the sharp one gives back the exposure it was made with
    (the excess across the motion, here a constant 0.3 px², does not count)."""
    sys.path.insert(0, str(CONCEALED.parent))
    diag = _load("diagnose", CONCEALED.parent / "diagnose.py")
    widths = diag._ramp_width(np.array([4.0, 12.0]), 0.01)
    assert widths == pytest.approx([4.0, 12.0], rel=1e-3)
    assert diag._ramp_width(np.array([0.0]), 1.5)[0] == pytest.approx(6 * 1.5 / np.sqrt(np.pi), rel=1e-4)
    assert diag._ramp_width(np.array([6.0]), 1.0)[0] > diag._ramp_width(np.array([4.0]), 1.0)[0]

    rng = np.random.default_rng(3)
    frames, w, fraction = 30, 0.25, 0.4
    velocity = rng.normal(0, 8, (frames, 2))
    along = velocity / np.linalg.norm(velocity, axis=1, keepdims=True)
    across = np.stack((-along[:, 1], along[:, 0]), 1)
    sharp = np.array([[30.0, 4.0], [4.0, 20.0]])
    blurred = (sharp + w / 2 * fraction**2 * np.einsum("ti,tj->tij", velocity, velocity)
               + 0.3 * np.einsum("ti,tj->tij", across, across))

    def raw(cov, area=500.0, centre=(100.0, 80.0)):
        cov = np.broadcast_to(cov, (frames, 2, 2))
        cu, cv = centre
        return np.stack([np.full(frames, area), np.full(frames, area * cu), np.full(frames, area * cv),
                         area * (cov[:, 0, 0] + cu * cu), area * (cov[:, 0, 1] + cu * cv),
                         area * (cov[:, 1, 1] + cv * cv)], -1)

    used = np.ones(frames, bool)
    assert diag._along_motion_fraction(raw(blurred), raw(sharp), velocity, used, w) == pytest.approx(fraction, rel=1e-6)
    assert diag._along_motion_fraction(raw(sharp), raw(sharp), velocity, used, w) == pytest.approx(0.0, abs=1e-6)




def test_subframe_poses_sit_where_the_recordings_put_them():
    """``diagnose._subframe_poses`` places a blurred recording's sub-frames evenly over its
    exposure, centred on the frame (make_recordings.sample_times), and a sharp recording's one
    sub-frame at the frame's own time, not half an exposure early."""
    sys.path.insert(0, str(CONCEALED.parent))
    diag = _load("diagnose", CONCEALED.parent / "diagnose.py")
    times = np.arange(8) / 30.0
    position = np.stack([1.0 + 2.0 * times, -4.9 * times**2, 3.0 + 0.0 * times], -1)  # a fall: the spline is exact
    truth = {"fps": 30.0, "per_frame": {"time": times.tolist(), "position": position.tolist(),
                                         "R": [np.eye(3).tolist()] * len(times)},
             "render": {"blur_subframes": 1, "exposure_frac": 0.5}}
    sharp, _ = diag._subframe_poses(truth)
    assert sharp.shape == (8, 1, 3) and np.allclose(sharp[:, 0], position)
    truth["render"]["blur_subframes"] = 5
    blurred, rotation = diag._subframe_poses(truth)
    offsets = (np.arange(5) / 4 - 0.5) * 0.5 / 30.0
    expected = times[:, None] + offsets
    assert np.allclose(blurred[..., 0], 1.0 + 2.0 * expected) and np.allclose(blurred[..., 1], -4.9 * expected**2)
    assert rotation.shape == (8, 5, 3, 3)

def test_radial_fit_recovers_a_lens_left_over():
    """``diagnose.py lens-residual``'s fit: centroids moved by a radial term ``d k1`` (the
    distortion ``x_n (1 + d k1 r_n^2)`` through K), an offset and 0.1 px of noise give ``d k1`` back
    within three of its standard errors, and that error is about what the noise makes; without the
    radial term the fit reads zero."""
    sys.path.insert(0, str(CONCEALED.parent))
    diag = _load("diagnose", CONCEALED.parent / "diagnose.py")
    K = np.array([[659.4, 0.0, 319.5], [0.0, 659.4, 239.5], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(5)
    true = rng.uniform((40.0, 40.0), (600.0, 440.0), (200, 2))
    normal = (true - K[:2, 2]) / K[0, 0]

    def seen(k1):
        moved = normal * (1 + k1 * (normal**2).sum(1, keepdims=True))
        return moved * K[0, 0] + K[:2, 2] + (0.05, -0.08) + rng.normal(0.0, 0.1, true.shape)

    fit = diag.radial_fit(seen(0.004), true, K)
    assert abs(fit["residual_k1"] - 0.004) < 3 * fit["residual_k1_std"]
    assert 1e-4 < fit["residual_k1_std"] < 1e-3
    assert fit["offset_px"] == pytest.approx([0.05, -0.08], abs=0.05)
    assert fit["centroid_rms_px"] == pytest.approx(0.1, rel=0.15)
    assert fit["signature_px"] == pytest.approx(float(np.abs(K[0, 0] * normal * (normal**2).sum(1, keepdims=True)).max()))
    null = diag.radial_fit(seen(0.0), true, K)
    assert abs(null["residual_k1"]) < 3 * null["residual_k1_std"]

def test_frame_noise_reads_the_noise_not_the_trend():
    """``diagnose.py end-frames``' noise unit is discover's floor: on a channel that is a smooth
    trend (a hundred times the noise over the clip) plus AR(1) noise of spread 0.3 with discover's
    lag-one correlation, a few jumps and a few failed (NaN) frames, it reads 0.3 within 10 %."""
    sys.path.insert(0, str(CONCEALED.parent))
    diag = _load("diagnose", CONCEALED.parent / "diagnose.py")
    from torchfit.discover_video import FRAME_CORRELATION as rho

    rng = np.random.default_rng(3)
    t = np.linspace(-1.0, 1.0, 2000)
    noise = np.zeros_like(t)
    for i in range(1, len(t)):
        noise[i] = rho * noise[i - 1] + rng.normal(0.0, 0.3 * np.sqrt(1 - rho**2))
    assert diag._frame_noise(noise) == pytest.approx(0.3, rel=0.1)
    jumped = 15.0 * t + 3.0 * t**2 + noise
    jumped[::250] += 5.0
    jumped[7::400] = np.nan
    assert diag._frame_noise(jumped) == pytest.approx(0.3, rel=0.1)
    assert np.ptp(15.0 * t + 3.0 * t**2) >= 99 * 0.3  # the trend spans a hundred times the noise


def test_lag_one_reads_the_noise_correlation_not_the_trend():
    """``diagnose.py frame-correlation``'s lag-one correlation: on AR(1) noise of correlation 0.4 or
    0.7 under a smooth trend a hundred times its size, with a few failed (NaN) frames, it reads the
    correlation within 0.06; on independent noise, 0 within 0.06."""
    sys.path.insert(0, str(CONCEALED.parent))
    diag = _load("diagnose", CONCEALED.parent / "diagnose.py")
    rng = np.random.default_rng(5)
    t = np.linspace(-1.0, 1.0, 4000)
    for rho in (0.0, 0.4, 0.7):
        noise = np.zeros_like(t)
        for i in range(1, len(t)):
            noise[i] = rho * noise[i - 1] + rng.normal(0.0, 0.3 * np.sqrt(1 - rho**2))
        series = 15.0 * t + 3.0 * t**2 + noise
        series[11::500] = np.nan
        assert diag._lag_one(series) == pytest.approx(rho, abs=0.06)


def test_mixed_moments_take_each_part_from_its_source():
    """``diagnose.py exact-coverage``'s mix: each of area, centroid and shape (second moments per
    unit area) comes from the source named, and an empty frame stays empty."""
    sys.path.insert(0, str(CONCEALED.parent))
    diag = _load("diagnose", CONCEALED.parent / "diagnose.py")
    from torchfit.losses import central_moments

    def raw(area, cu, cv, a, b, c):
        return [area, area * cu, area * cv, area * (a + cu * cu), area * (b + cu * cv), area * (c + cv * cv)]

    seen = np.array([raw(100.0, 10.0, 20.0, 9.0, 1.0, 8.0), raw(120.0, 11.0, 21.0, 9.5, 0.5, 8.5), [0.0] * 6])
    exact = np.array([raw(104.0, 10.5, 19.0, 10.0, 2.0, 7.0), raw(118.0, 11.2, 20.5, 9.0, 0.0, 9.0),
                      raw(90.0, 12.0, 22.0, 8.0, 0.0, 8.0)])
    assert np.allclose(diag.mixed_moments(seen, exact, ()), seen)
    assert np.allclose(diag.mixed_moments(seen, exact, diag.COVERAGE_PARTS)[:2], exact[:2])
    mixed = central_moments(torch.as_tensor(diag.mixed_moments(seen, exact, ("centroid",))[:2]))
    own, true = central_moments(torch.as_tensor(seen[:2])), central_moments(torch.as_tensor(exact[:2]))
    assert torch.allclose(mixed[0], own[0]) and torch.allclose(mixed[1], true[1]) and torch.allclose(mixed[2], own[2])
    assert np.all(diag.mixed_moments(seen, exact, ("area",))[2] == 0)
    # the shape's error split: spread (isotropic) and stretch (traceless) add up to the whole
    spread, stretch = (central_moments(torch.as_tensor(diag.mixed_moments(seen, exact, (p,))[:2]))[2]
                       for p in diag.SHAPE_PARTS)
    error = true[2] - own[2]
    assert torch.allclose(spread - own[2], error.diagonal(dim1=-2, dim2=-1).mean(-1)[:, None, None] * torch.eye(2,
                                                                                     dtype=torch.float64))
    assert torch.allclose((spread - own[2]) + (stretch - own[2]), error)
    assert torch.allclose(stretch[:, 0, 0] + stretch[:, 1, 1], own[2][:, 0, 0] + own[2][:, 1, 1])
    assert np.allclose(diag.mixed_moments(seen, exact, diag.SHAPE_PARTS), diag.mixed_moments(seen, exact, ("shape",)))


def test_blur_speed_bands_reach_as_far_as_named():
    """``diagnose.py blur-speed``'s bands around a one-pixel mask: 4-neighbour steps reach a
    diamond, Euclidean px a disc, px past half the travel a disc wider by half the frame's
    travel (as far as any exposure's blur reaches), and the steps swept along the motion the
    diamond stretched by half the travel either way along it and no wider across it."""
    sys.path.insert(0, str(CONCEALED.parent))
    diag = _load("diagnose", CONCEALED.parent / "diagnose.py")
    mask = np.zeros((21, 21), bool)
    mask[10, 10] = True
    steps, disc = diag._band(mask, "steps", 3), diag._band(mask, "px", 3)
    assert steps[10, 13] and not steps[12, 12] and disc[12, 12] and not disc[10, 14]
    assert steps.sum() == 25 and disc.sum() == 29
    wide = diag._band(mask, "px past half the travel", 2, velocity=np.array([0.0, 4.0]))
    assert np.array_equal(wide, diag._band(mask, "px", 4))
    swept = diag._band(mask, "steps and half the travel along it", 3, velocity=np.array([4.0, 0.0]))
    assert swept.sum() == 25 + 4 * 7 and swept[10, 15] and not swept[10, 16] and not swept[14, 10]


def test_contrast_oracle_replaces_the_lowest_contrast_share_of_the_ramp_first():
    """``diagnose.py contrast-oracle``'s one frame: a disc's coverage read 0.5 short on the ramp's
    right half, whose pixels are also the lowest in contrast. Replacing the lowest half of the
    ramp by the exact coverage removes the whole centroid error; the same share drawn at random
    removes about half of it; the ramp made exact removes it all; nothing replaced keeps it, a
    shift to the left."""
    sys.path.insert(0, str(CONCEALED.parent))
    diag = _load("diagnose", CONCEALED.parent / "diagnose.py")
    v, u = np.mgrid[0:41, 0:41]
    exact = np.clip(10.5 - np.hypot(u - 20, v - 20), 0.0, 1.0)
    ramp = (exact > 0.02) & (exact < 0.98)
    right = ramp & (u > 20)
    cover = np.where(right, exact - 0.5 * exact, exact)
    level = np.where(right, 5.0, 50.0) + 0.01 * u  # the right half lowest, in pixel order within it
    assert 0.45 < right.sum() / ramp.sum() <= 0.5
    errors = diag._oracle_errors(cover, exact, level, ramp, np.random.default_rng(0))
    x, y = errors["as segmented"]
    assert x < -0.05 and abs(y) < 1e-9
    assert abs(errors["lowest 0.5"][0]) < 1e-9 and abs(errors["ramp exact"][0]) < 1e-9
    assert 0.3 * abs(x) < abs(errors["random 0.5"][0]) < 0.7 * abs(x)
    assert abs(errors["lowest 0.25"][0]) < abs(x) and abs(errors["lowest 0.1"][0]) < abs(x)


def test_replay_selection_reruns_forward_selection_from_stored_scores():
    """Two rounds stored: the clock named, then nothing. The replay reproduces it; with the
    held-out test decided by the RMS rule the clock (held-out 10 % worse, 2.4 floors) is vetoed,
    and the drag it would name instead was never scored after the clock: not exact."""
    replay = _load("replay_selection", CONCEALED.parent / "replay_selection.py")

    def score(bic, fails, gain=0.0, after=1.0, rise=0.0):
        return {"delta_bic": bic, "fails": fails, "heldout_gain": gain, "heldout_rms_after": after,
                "heldout_deviance_rise": rise}

    content = {"verdict": ["time_scale"], "effects": {
        "time_scale": [score(60.0, [], gain=-0.10, after=2.4, rise=2.0)],
        "quadratic_drag": [score(30.0, []), score(4.0, ["delta_bic"])]}}
    assert replay.replay(content) == (["time_scale"], None, True)
    assert replay.replay(content, heldout=replay.rms_rule) == (["quadratic_drag"], None, False)
    assert replay.replay(content, heldout=replay.deviance_rule(1.0)) == (["quadratic_drag"], None, False)
    assert replay.replay(content, heldout=replay.deviance_rule(6.0)) == (["time_scale"], None, True)
    # a look-alike within the margin stops the replay with both reported
    content["effects"]["quadratic_drag"][0]["delta_bic"] = 55.0
    assert replay.replay(content) == ([], ["time_scale", "quadratic_drag"], True)


def test_replay_selection_decides_the_bar_again():
    """``min_delta_bic``: the ΔBIC and Wald tests are decided against the bar given. A clock at
    ΔBIC 8 (Wald 7) failed both at the runs' bar of 10; at 5 it passes, at 7.5 its Wald fails; a
    failure of another test stays; the stored run never scored the round after it: not exact."""
    replay = _load("replay_selection", CONCEALED.parent / "replay_selection.py")
    clock = {"delta_bic": 8.0, "wald_delta_bic": 7.0, "fails": ["delta_bic", "wald"]}
    content = {"verdict": [], "effects": {"time_scale": [clock]}}
    assert replay.replay(content) == ([], None, True)
    assert replay.replay(content, min_delta_bic=10.0) == ([], None, True)
    assert replay.replay(content, min_delta_bic=7.5) == ([], None, True)
    assert replay.replay(content, min_delta_bic=5.0) == (["time_scale"], None, False)
    assert replay.replay(content, drop=("wald",), min_delta_bic=7.5) == (["time_scale"], None, False)
    clock["fails"].append("evidence_spread")
    assert replay.replay(content, min_delta_bic=5.0) == ([], None, True)


def test_replay_selection_lists_where_two_variants_differ(tmp_path):
    """``differences``: a recording whose replayed verdicts differ is listed, one that agrees is
    not, one run only one way is skipped; under the RMS rule a clock that predicts the held-out
    frames 10 % worse is vetoed on one side only, and listed."""
    replay = _load("replay_selection", CONCEALED.parent / "replay_selection.py")

    def run(folder, name, named, gain=0.1):
        score = {"delta_bic": 60.0 if named else 1.0, "fails": [] if named else ["delta_bic"],
                 "heldout_gain": gain, "heldout_rms_after": 2.4, "heldout_deviance_rise": 0.0}
        rounds = [score] + ([{**score, "delta_bic": 1.0, "fails": ["delta_bic"]}] if named else [])
        content = {"verdict": ["time_scale"] if named else [], "truth_effects": {"time_scale": {}},
                   "indistinguishable": [], "effects": {"time_scale": rounds}}
        (folder / name).mkdir(parents=True)
        (folder / name / "discover.json").write_text(json.dumps(content))

    first, second = tmp_path / "a", tmp_path / "b"
    run(first, "same", True)
    run(second, "same", True)
    run(first, "moved", True)
    run(second, "moved", False)
    run(first, "alone", True)
    assert [line.split()[0] for line in replay.differences(first, second)] == ["moved"]
    run(first, "vetoed", True, gain=-0.10)
    run(second, "vetoed", True)
    assert [line.split()[0] for line in replay.differences(first, second)] == ["moved"]
    lines = replay.differences(first, second, heldout=replay.rms_rule)
    assert [line.split()[0] for line in lines] == ["moved", "vetoed"]
    assert "[] against ['time_scale']" in lines[1]


def test_coefficients_compares_right_names_with_the_truth():
    """coefficients.py counts a run only when its verdict is exactly the hidden effect, and reads
    the ratio and the error in standard errors from the final model's parameters."""
    coefficients = _load("coefficients", CONCEALED.parent / "coefficients.py")

    def run(verdict, value, std, truth=0.5):
        return {"truth_effects": {"quadratic_drag": {"drag_coefficient": truth}}, "verdict": verdict,
                "models": [{"params": {}}, {"params": {"quadratic_drag": {"drag_coefficient": {"value": value, "std": std}}}}]}

    assert coefficients.coefficient_rows(run([], 0.6, 0.05)) == []  # missed: no coefficient
    assert coefficients.coefficient_rows(run(["quadratic_drag", "magnus"], 0.6, 0.05)) == []  # a wrong second name
    assert coefficients.coefficient_rows({"truth_effects": {}, "verdict": [], "models": []}) == []  # a control
    rows = coefficients.coefficient_rows(run(["quadratic_drag"], 0.6, 0.05)) + \
        coefficients.coefficient_rows(run(["quadratic_drag"], 0.45, 0.05))
    s = coefficients.summary(rows)["quadratic_drag.drag_coefficient"]
    assert s["n"] == 2 and s["ratio_min"] == pytest.approx(0.9) and s["ratio_max"] == pytest.approx(1.2)
    assert s["ratio_median"] == pytest.approx(1.05) and s["z_mean"] == pytest.approx(0.5)  # z = +2 and -1
    assert s["z_rms"] == pytest.approx(math.sqrt(2.5))


def test_coefficients_unselected_reads_every_first_round_fit_and_the_controls():
    """``--unselected``: the hidden parameter from the first round's fit of the hidden effect
    alone, named or not (a miss counts, a wrong second name does not change it), and the
    controls' first-round candidates' Wald statistics and chi-squared drops."""
    coefficients = _load("coefficients", CONCEALED.parent / "coefficients.py")

    def run(verdict, value, std):
        first = {"params": {"quadratic_drag": {"drag_coefficient": {"value": value, "std": std}}},
                 "delta_dof": 1, "wald_chi2": 9.0, "delta_chi2": 8.0}
        later = {"params": {"quadratic_drag": {"drag_coefficient": {"value": 9.0, "std": 1.0}}}}
        return {"truth_effects": {"quadratic_drag": {"drag_coefficient": 0.5}}, "verdict": verdict,
                "effects": {"quadratic_drag": [first, later]}, "models": []}

    assert coefficients.unselected_rows(run([], 0.7, 0.1)) == [("quadratic_drag", "drag_coefficient", 0.5, 0.7, 0.1)]
    assert coefficients.unselected_rows(run(["magnus", "quadratic_drag"], 0.4, 0.1))[0][3] == 0.4
    assert coefficients.control_rows(run([], 0.7, 0.1)) == []  # an effect recording is no control
    control = {"truth_effects": {}, "verdict": [], "effects": {
        "time_scale": [{"delta_dof": 1, "wald_chi2": 0.5, "delta_chi2": 0.7, "params": {}}],
        "lens_distortion": [{"delta_dof": 2, "wald_chi2": 2.5, "delta_chi2": 3.0, "params": {}}]}}
    assert coefficients.control_rows(control) == [("time_scale", 1, 0.5, 0.7), ("lens_distortion", 2, 2.5, 3.0)]
    assert coefficients.unselected_rows(control) == []


def test_segmentation_correlation_reads_shift_size_and_memory():
    """segmentation_correlation.py's errors: a mask moved by 2 px right and 1 px up reads (+2, -1)
    in centroid and 0 in scale, a larger one a positive scale error; an alternating error has
    autocorrelation near -1 at lag 1 and a slow one near +1."""
    pytest.importorskip("cv2")
    sys.path.insert(0, str(CONCEALED.parent))  # segmentation_correlation.py imports true_masks from its folder
    module = _load("segmentation_correlation", CONCEALED.parent / "segmentation_correlation.py")
    true = np.zeros((3, 20, 30), bool)
    true[:, 5:11, 8:16] = True
    moved = np.roll(np.roll(true, 2, axis=2), -1, axis=1)
    grown = true.copy()
    grown[2, 4:12, 7:17] = True
    raw = module.raw_moments  # the segmentation's masks' or coverage's raw moments, against the true masks
    errors = module.moment_errors(raw(moved), true)
    np.testing.assert_allclose(errors, [[2.0, -1.0, 0.0]] * 3, atol=1e-12)
    assert module.moment_errors(raw(grown), true)[2, 2] == pytest.approx(np.sqrt(80 / 48) - 1)
    half = raw(grown) * 0.5  # a coverage of one half everywhere the mask is: the same centroid, half the area
    np.testing.assert_allclose(module.moment_errors(half, grown)[:, :2], 0.0, atol=1e-12)
    assert module.moment_errors(half, grown)[0, 2] == pytest.approx(np.sqrt(0.5) - 1)
    assert module.moment_errors(raw(np.zeros_like(true)), true).shape == (0,)  # no frame with both
    t = np.arange(60.0)
    assert module.autocorrelation((-1.0) ** t, 1) < -0.95
    assert module.autocorrelation(np.sin(t / 20), 1) > 0.9


def test_search_outcomes_summary_counts_what_the_second_setting_changes():
    """search_outcomes.py --summary: a loss 2 % above the first setting's is counted worse, one
    74 % below better (with both rotation errors), one 0.5 % off is the largest other change; the
    seconds' ratio is the median of the rows'; lines run with other finals are refused."""
    sys.path.insert(0, str(CONCEALED.parent))
    so = _load("search_outcomes", CONCEALED.parent / "search_outcomes.py")

    def row(name, loss_a, loss_b, deg_a, deg_b, sec_b):
        return {"recording": name, "finals": ["6", "12"],
                "runs": {"12": {"loss": loss_b, "rotation_error_deg": deg_b, "seconds": sec_b},
                         "6": {"loss": loss_a, "rotation_error_deg": deg_a, "seconds": 10.0}}}
    rows = [row("a", 1.0, 1.02, 1.0, 1.0, 11.0), row("b", 1.0, 0.26, 17.3, 1.0, 12.0),
            row("c", 1.0, 1.005, 6.0, 6.0, 14.0), row("d", 1.0, 1.0, 1.0, 1.0, 13.0)]
    text = so.summary(rows)
    assert "more than 1 % above: 1 ['a']" in text
    assert "more than 1 % below: 1 b (-74.0 %: 17.3° → 1.0°)" in text
    assert "within 0.001 %: 1" in text
    assert "the largest other change: c (+0.500 %)" in text
    assert "from the truth: 2 ['b', 'c']" in text
    assert "median 1.25 (range 1.10–1.40)" in text
    with pytest.raises(ValueError, match="same two finals"):
        so.summary(rows + [{**rows[0], "finals": ["6", "9"]}])


def test_compare_runs_reports_verdicts_and_the_largest_score_change(tmp_path, capsys):
    """compare_runs.py: runs under both roots compared; a moved ΔBIC is found in the round it moved
    in, a changed verdict is listed, a run under one root only is left out; the predictions' lines
    that flag a channel are told apart per tree and counted on the controls."""
    compare = _load("compare_runs", CONCEALED.parent / "compare_runs.py")

    def write(root, name, verdict, bics, truth=None, flagged=()):
        folder = root / "concealed_x" / name
        folder.mkdir(parents=True)
        effects = {effect: [{"delta_bic": b} for b in rounds] for effect, rounds in bics.items()}
        lines = {"located_heldout": [{"part": "end", "flagged": list(flagged)}, {"part": "start", "flagged": []}],
                 "located_heldout_after": [{"part": "end", "flagged": []}]}
        (folder / "discover.json").write_text(json.dumps({"verdict": verdict, "effects": effects,
                                                          "indistinguishable": [], "truth_effects": truth or {},
                                                          **lines}))
    a, b = tmp_path / "a", tmp_path / "b"
    drag, clock = {"quadratic_drag": {"drag_coefficient": 0.5}}, {"time_scale": {"time_scale": 1.02}}
    write(a, "drag", ["quadratic_drag"], {"quadratic_drag": [40.0], "time_scale": [3.0, 1.0]}, drag, ["centroid_x"])
    write(b, "drag", ["quadratic_drag"], {"quadratic_drag": [40.1], "time_scale": [3.0, 1.5]}, drag, ["centroid_x"])
    write(a, "clock", [], {"time_scale": [9.0]}, clock)
    write(b, "clock", ["time_scale"], {"time_scale": [12.0]}, clock)
    write(a, "only_here", [], {"time_scale": [1.0]})
    write(a, "control", [], {"magnus": [-2.0]}, flagged=["shape"])
    write(b, "control", [], {"magnus": [-2.0]})
    result = compare.compare(a, b)
    control = result["runs"].pop(1)
    assert control["control"] and not control["right"] and result["runs"][1]["right"] and not result["runs"][0]["right"]
    assert control["flags"] == {"located_heldout": [True, False], "located_heldout_after": [False, False]}
    assert [r["run"] for r in result["runs"]] == ["concealed_x/clock", "concealed_x/drag"]
    assert [r["run"] for r in result["differ"]] == ["concealed_x/clock"]
    drag = result["runs"][1]
    assert drag["largest_delta_bic_change"] == pytest.approx(0.5) and drag["where"] == ["time_scale", 1]
    assert compare.main([str(a), str(b), "--out", str(tmp_path / "c.json")]) == 0
    out = capsys.readouterr().out
    assert "controls, 1 runs: the baseline's predictions flag a channel on 1 (first) and 0 (second)" in out
    assert "named right (first tree), 1 runs: the baseline's predictions flag a channel on 1 (first) and 1 (second)" in out
    assert json.loads((tmp_path / "c.json").read_text())["largest"][0]["run"] == "concealed_x/clock"


def test_shake_maps_agree_with_camera_motion_and_a_pan_moves_the_principal_point_by_f_tan():
    """``shake.py``'s maps of a still pixel to the frame's: a shift and turn of the picture is
    ``camera_motion``'s own map (``_motion_matrices``); a camera rolled by ``r`` turns the picture
    by ``-r`` in that convention; a pan by ``a`` moves the principal point by ``f tan a`` across and
    a corner by more, ``f tan(atan(x / f) + a) - x``, to first order what a shift leaves out."""
    sys.path.insert(0, str(CONCEALED.parent))
    shake = _load("shake", CONCEALED.parent / "shake.py")
    from torchfit.video import _motion_matrices

    size, camera = (480, 640), {"fx": 659.0, "fy": 659.0, "cx": 319.5, "cy": 239.5}
    rows = np.array([[1.5, -0.5, 0.3], [0.0, 2.0, -0.7]])
    record = {"offsets_px": rows[:, :2].tolist(), "roll_deg": rows[:, 2].tolist()}
    np.testing.assert_allclose(shake.shake_maps(record, size), _motion_matrices(rows, size), atol=1e-12)
    rolled = shake.turn_maps(np.zeros((1, 2)), np.zeros((1, 2)), np.array([0.7]), camera)
    np.testing.assert_allclose(rolled, _motion_matrices(np.array([[0.0, 0.0, -0.7]]), size), atol=1e-9)
    pan = np.radians(0.2)
    panned = shake.turn_maps(np.zeros((1, 2)), np.array([[0.2, 0.0]]), np.zeros(1), camera)[0]
    for x in (0.0, 320.0):
        point = panned @ np.array([319.5 + x, 239.5, 1.0])
        assert point[0] / point[2] - 319.5 - x == pytest.approx(659.0 * np.tan(np.arctan(x / 659.0) + pan) - x)
        assert point[1] / point[2] == pytest.approx(239.5)
    assert shake.shake_maps(record | {"maps": panned[None].tolist()}, size)[0] == pytest.approx(panned)


def test_error_moved_keeps_each_frames_error_and_moves_it_to_another_frame():
    """``true_masks.error_moved``: the identity order gives the segmented moments back; a shuffled
    order puts frame j's centroid offset and area ratio on frame k (where order[k] = j), and its
    second moments' offset relative to the object's size squared; an empty frame keeps the
    segmentation's; an order that does not permute the usable frames is refused, naming it."""
    sys.path.insert(0, str(CONCEALED.parent))
    tm = _load("true_masks", CONCEALED.parent / "true_masks.py")
    from torchfit.video import raw_moments

    rng = np.random.default_rng(0)
    exact_masks = np.zeros((5, 40, 50), bool)
    seg_masks = np.zeros((5, 40, 50), bool)
    for t in range(4):  # frame 4 empty in both
        exact_masks[t, 10 + t:20 + t, 5 + 3 * t:19 + 3 * t] = True
        seg_masks[t, 10 + t + rng.integers(0, 2):21 + t, 5 + 3 * t + rng.integers(0, 3):18 + 3 * t] = True
    exact, seg = raw_moments(exact_masks), raw_moments(seg_masks)
    np.testing.assert_allclose(tm.error_moved(seg, exact, np.arange(4)), seg, rtol=1e-12, atol=1e-9)
    order = np.array([2, 0, 3, 1])
    moved = tm.error_moved(seg, exact, order)
    from torchfit.losses import central_moments

    def central(raw):  # area, centroid, central second moments (mu20, mu11, mu02)
        area, centroid, cov = (x.numpy() for x in central_moments(torch.as_tensor(raw, dtype=torch.float64)))
        return area, centroid, cov.reshape(-1, 4)[:, [0, 1, 3]]

    a_e, c_e, s_e = central(exact[:4])
    a_s, c_s, s_s = central(seg[:4])
    a_m, c_m, s_m = central(moved[:4])
    np.testing.assert_allclose(a_m / a_e, (a_s / a_e)[order], rtol=1e-12)
    np.testing.assert_allclose(c_m - c_e, (c_s - c_e)[order], atol=1e-9)
    size = s_e[:, 0] + s_e[:, 2]  # the second moments' error moves relative to the object's size squared
    np.testing.assert_allclose((s_m - s_e) / size[:, None], ((s_s - s_e) / size[:, None])[order], atol=1e-12)
    np.testing.assert_array_equal(moved[4], seg[4])
    with pytest.raises(ValueError, match="permute the 4 frames"):
        tm.error_moved(seg, exact, np.array([0, 1, 1, 2]))


def test_exact_centroids_keep_the_area_and_spread_and_touch_only_their_frames():
    """centroid_oracle.with_exact_centroids: the named frames take the exact moments' centroid and
    keep their own area and covariance; the other frames and an empty range are left as they are."""
    import numpy as np
    import torch

    from torchfit.losses import central_moments, raw_from_central

    sys.path.insert(0, str(CONCEALED.parent))
    oracle = _load("centroid_oracle", CONCEALED.parent / "centroid_oracle.py")
    area = torch.tensor([100.0, 120.0, 90.0])
    cov = torch.tensor([[[30.0, 4.0], [4.0, 20.0]]] * 3, dtype=torch.float64)
    seen = raw_from_central(area.double(), torch.tensor([[10.0, 20.0], [11.0, 22.0], [12.0, 24.0]]).double(), cov).numpy()
    exact = raw_from_central(torch.tensor([95.0, 118.0, 91.0]).double(),
                             torch.tensor([[10.5, 19.0], [11.5, 21.5], [12.5, 23.0]]).double(), 0.5 * cov).numpy()
    moved = oracle.with_exact_centroids(seen, exact, 1, 1)
    a, c, s = central_moments(torch.as_tensor(moved))
    assert torch.allclose(a, area.double()) and torch.allclose(s, cov)
    assert torch.allclose(c[1], torch.tensor([11.5, 21.5]).double())
    assert np.array_equal(moved[[0, 2]], seen[[0, 2]])
    assert np.array_equal(oracle.with_exact_centroids(seen, exact, 3, 2), seen)
