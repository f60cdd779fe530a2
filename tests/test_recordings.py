"""Checks of the shipped MuJoCo test recordings (torchfit/recordings).

Everything but the last test needs only numpy / cv2 / trimesh / scipy (no MuJoCo,
no torchfit): the ground truth is checked against the mesh, the masks and the laws
of free flight. The regeneration test is marked ``recordings`` (needs the
``[recordings]`` extra, i.e. MuJoCo, and MUJOCO_GL=osmesa or egl).
"""
from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "torchfit" / "recordings"
SCRIPT = ROOT / "experiments" / "recordings" / "make_recordings.py"
SHIPPED = ["tshape", "tshape_intermediate", "box_fast", "cylinder", "tshape_small"]


def load(name):
    d = DATA / name
    truth = json.loads((d / "truth.json").read_text())
    cam = json.loads((d / "camera.json").read_text())
    with np.load(d / truth["masks"]) as z:
        masks = z["masks"].astype(bool)
    mesh = trimesh.load(d / truth["object"]["mesh"], force="mesh", process=False)
    return d, truth, cam, masks, mesh


def quat_to_mat(q):
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def silhouette(vertices, faces, R, t, cam, S=31):
    """Pixels whose centre lies inside the projected mesh (OpenCV pinhole, pixel
    (0,0)'s centre at (0,0)); triangles filled with cv2 at S x resolution (S odd)."""
    H, W = cam["height"], cam["width"]
    pc = vertices @ np.asarray(R).T + np.asarray(t)
    assert pc[:, 2].min() > 0
    uv = np.stack([cam["fx"] * pc[:, 0] / pc[:, 2] + cam["cx"],
                   cam["fy"] * pc[:, 1] / pc[:, 2] + cam["cy"]], axis=1)
    out = np.zeros((H, W), bool)
    x0, y0 = max(int(np.floor(uv[:, 0].min())) - 1, 0), max(int(np.floor(uv[:, 1].min())) - 1, 0)
    x1 = min(int(np.ceil(uv[:, 0].max())) + 1, W - 1)
    y1 = min(int(np.ceil(uv[:, 1].max())) + 1, H - 1)
    if x1 < x0 or y1 < y0:
        return out
    img = np.zeros(((y1 - y0 + 1) * S, (x1 - x0 + 1) * S), np.uint8)
    pts = np.round(((uv - [x0, y0]) * S + S // 2) * 16.0).astype(np.int32)
    for f in faces:
        cv2.fillConvexPoly(img, pts[f], 1, lineType=cv2.LINE_8, shift=4)
    out[y0:y1 + 1, x0:x1 + 1] = img[S // 2::S, S // 2::S].astype(bool)
    return out


def rel(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300))


@pytest.fixture(params=SHIPPED)
def rec(request):
    return load(request.param)


def test_files_and_schema(rec):
    d, truth, cam, masks, mesh = rec
    for k in ("fx", "fy", "cx", "cy", "width", "height"):
        assert k in cam
    W, H = cam["width"], cam["height"]
    assert cam["cx"] == pytest.approx((W - 1) / 2) and cam["cy"] == pytest.approx((H - 1) / 2)
    assert cam["fx"] == pytest.approx(cam["fy"])
    assert truth["g"] == 9.81
    tilt, roll = math.radians(truth["tilt_deg"]), math.radians(truth["roll_deg"])
    d_expected = [math.sin(roll) * math.cos(tilt), math.cos(roll) * math.cos(tilt), math.sin(tilt)]
    np.testing.assert_allclose(truth["gravity_dir"], d_expected, atol=1e-9)
    pf = truth["per_frame"]
    T = len(pf["frame"])
    assert masks.shape == (T, H, W)
    np.testing.assert_allclose(pf["time"], np.arange(T) / truth["fps"], atol=1e-12)
    for k in ("position", "orientation_wxyz", "R", "bbox"):
        assert len(pf[k]) == T
    # params are the state at frame 0; quaternions and matrices agree
    p = truth["params"]
    np.testing.assert_allclose(pf["position"][0], p["position"], atol=1e-9)
    np.testing.assert_allclose(pf["R"][0], p["R"], atol=1e-9)
    np.testing.assert_allclose(quat_to_mat(p["orientation_wxyz"]), p["R"], atol=1e-9)
    for q, R in zip(pf["orientation_wxyz"], pf["R"]):
        np.testing.assert_allclose(quat_to_mat(q), R, atol=1e-9)
    # bbox = bounding box of the true mask; object fully in view, off the border
    for m, bb in zip(masks, pf["bbox"]):
        ys, xs = np.nonzero(m)
        assert len(xs) > 0
        assert bb == [xs.min(), ys.min(), xs.max(), ys.max()]
        assert bb[0] > 0 and bb[1] > 0 and bb[2] < W - 1 and bb[3] < H - 1
    # the video decodes to the right number / size of frames
    cap = cv2.VideoCapture(str(d / "video.mp4"))
    n = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        assert frame.shape == (H, W, 3)
        n += 1
    cap.release()
    assert n == T


def test_mass_properties(rec):
    _, truth, _, _, mesh = rec
    obj = truth["object"]
    assert obj["density"] == 600.0
    mesh.density = 600.0
    assert mesh.mass == pytest.approx(obj["mass"], rel=1e-3)
    assert rel(mesh.center_mass, obj["com"]) < 1e-3 or np.allclose(mesh.center_mass, obj["com"],
                                                                    atol=1e-6)
    assert rel(mesh.moment_inertia, obj["inertia"]) < 1e-3


def test_masks_match_projected_mesh(rec):
    _, truth, cam, masks, mesh = rec
    V, F = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    pf = truth["per_frame"]
    ious = []
    for R, t, m in zip(pf["R"], pf["position"], masks):
        s = silhouette(V, F, R, t, cam)
        ious.append((s & m).sum() / (s | m).sum())
    assert min(ious) >= 0.95, ious


def test_free_flight(rec):
    """COM on a parabola with acceleration g * gravity_dir; params' velocity is the
    mesh origin's; rotation = torque-free Euler motion from params' angular velocity."""
    from scipy.integrate import solve_ivp

    _, truth, _, _, _ = rec
    pf, p, obj = truth["per_frame"], truth["params"], truth["object"]
    t = np.asarray(pf["time"])
    R = np.asarray(pf["R"])
    com = np.asarray(obj["com"])
    c = np.asarray(pf["position"]) + R @ com
    A = np.stack([np.ones_like(t), t, 0.5 * t ** 2], axis=1)
    coef, *_ = np.linalg.lstsq(A, c, rcond=None)
    g = truth["g"] * np.asarray(truth["gravity_dir"])
    assert rel(coef[2], g) < 1e-3
    assert np.abs(A @ coef - c).max() < 1e-6  # it is a parabola
    # velocity of the mesh origin at t=0: v_com + w x (origin - com)
    w0 = np.asarray(p["angular_velocity"])
    R0 = np.asarray(p["R"])
    v_origin = coef[1] + np.cross(w0, -R0 @ com)
    assert rel(p["velocity"], v_origin) < 1e-3
    np.testing.assert_allclose(coef[0] - R0 @ com, p["position"], atol=1e-6)

    # orientation: integrate Euler's equations (body frame) from params, compare
    I = np.asarray(obj["inertia"])
    Iinv = np.linalg.inv(I)

    def f(_, y):
        Rm, wb = y[:9].reshape(3, 3), y[9:]
        dR = Rm @ np.array([[0, -wb[2], wb[1]], [wb[2], 0, -wb[0]], [-wb[1], wb[0], 0]])
        return np.concatenate([dR.ravel(), -Iinv @ np.cross(wb, I @ wb)])

    sol = solve_ivp(f, (0, t[-1]), np.concatenate([R0.ravel(), R0.T @ w0]), t_eval=t,
                    method="DOP853", rtol=1e-11, atol=1e-12)
    Rint = sol.y[:9].T.reshape(-1, 3, 3)
    assert np.abs(Rint - R).max() < 1e-4


@pytest.mark.recordings
def test_regenerate_small(tmp_path):
    """Regenerating tshape_small with MuJoCo reproduces the shipped ground truth."""
    spec_ = importlib.util.spec_from_file_location("make_recordings", SCRIPT)
    mr = importlib.util.module_from_spec(spec_)
    sys.modules["make_recordings"] = mr  # dataclasses need the module registered
    spec_.loader.exec_module(mr)
    mr.offscreen_gl()  # before mujoco is imported
    pytest.importorskip("mujoco")
    spec = next(s for s in mr.shipped_specs() if s.name == "tshape_small")
    summary = mr.make_recording(spec, tmp_path, verbose=False)
    assert summary["iou_min"] >= 0.95
    new = json.loads((tmp_path / "tshape_small" / "truth.json").read_text())
    old = json.loads((DATA / "tshape_small" / "truth.json").read_text())
    for k in ("position", "R"):
        np.testing.assert_allclose(new["per_frame"][k], old["per_frame"][k], atol=1e-6)
    for k in ("position", "velocity", "angular_velocity"):
        np.testing.assert_allclose(new["params"][k], old["params"][k], atol=1e-6)
    with np.load(tmp_path / "tshape_small" / "masks.npz") as z:
        m_new = z["masks"]
    with np.load(DATA / "tshape_small" / "masks.npz") as z:
        m_old = z["masks"]
    assert (m_new != m_old).mean() < 1e-3


@pytest.mark.parametrize("name", SHIPPED)
def test_torchfit_camera_and_renderer_land_on_mujoco_masks(name):
    """Conventions between the two engines: torchfit's camera and renderer at the true poses
    reproduce MuJoCo's own segmentation, IoU >= 0.95 on every frame."""
    import torch

    from torchfit.camera import Camera
    from torchfit.render import RenderMesh, full_window, render_silhouettes
    from torchfit.shape import load_shape

    folder = DATA / name
    truth = json.loads((folder / "truth.json").read_text())
    camera = Camera.from_file(folder / "camera.json")
    shape = load_shape(folder / "mesh.obj", density=truth["object"]["density"])
    rot = torch.tensor(truth["per_frame"]["R"], dtype=torch.float64)
    trans = torch.tensor(truth["per_frame"]["position"], dtype=torch.float64)
    ours = render_silhouettes(RenderMesh.from_shape(shape, torch.float64), camera, rot[None], trans[None],
                              full_window(camera, 1, len(rot), dtype=torch.float64),
                              size=(camera.height, camera.width), sigma=None)[0].numpy() > 0.5
    with np.load(folder / "masks.npz") as data:
        masks = data[data.files[0]].astype(bool)
    iou = (ours & masks).sum((1, 2)) / np.maximum((ours | masks).sum((1, 2)), 1)
    assert iou.min() >= 0.95, (name, iou.min())
