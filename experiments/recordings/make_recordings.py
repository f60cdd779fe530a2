#!/usr/bin/env python
"""Synthetic test recordings of a thrown rigid body, made with MuJoCo.

MuJoCo does both the physics (free flight, RK4) and the rendering (its own
OpenGL renderer, offscreen), so the recordings are independent of torchfit.
Every recording comes with exact ground truth in the camera frame, and is
checked on creation: the mesh written to ``mesh.obj``, projected with the
pinhole model of ``camera.json`` at the true pose of each frame, must match
MuJoCo's own segmentation render of that instant (IoU >= 0.95 on every frame).

Regenerate the shipped set (from the repository root)::

    MUJOCO_GL=osmesa python experiments/recordings/make_recordings.py --out torchfit/recordings

Other uses::

    ... make_recordings.py --out torchfit/recordings --only tshape_small
    ... make_recordings.py --out /tmp/rec --spec name=mybox shape=box spin_rate=5.0 seed=3

or from Python::

    from make_recordings import RecordingSpec, make_recording
    make_recording(RecordingSpec(name="x", shape="box", seed=1), "/tmp/rec")

Conventions (contracts, see README.md):
  * camera frame = OpenCV: x right, y down, z forward; pixel (0,0)'s centre at (0,0);
    fx = fy = (H/2)/tan(fovy/2), cx = (W-1)/2, cy = (H-1)/2.
  * all ground truth is in the camera frame; gravity = g * d(tilt, roll),
    d = (sin(roll)cos(tilt), cos(roll)cos(tilt), sin(tilt)).
  * pose: X_cam = R @ X_obj + t, X_obj = coordinates of mesh.obj (metres);
    quaternions (w, x, y, z); angular velocity in rad/s in the camera frame;
    velocity = velocity of the mesh origin in the camera frame; frame i at t = i/fps.
"""
from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Optional, Sequence

import cv2
import numpy as np
import trimesh

G = 9.81
MJ_OBJ_GEOM = 5  # mujoco.mjtObj.mjOBJ_GEOM
# Through a lens the true mask is resampled from the wide pinhole render. A binary mask resampled
# by nearest neighbour moves each edge by up to half a pixel, coherently over tens of pixels (where
# the map's fractional part drifts slowly), so the masks' centroids erred by 0.34 px RMS against
# the mesh projected through the same lens (fresh-3 lens_tshape; 0.03 px on its control). The mask
# is therefore rendered at this many samples per wide pixel along each axis, box-filtered to a
# coverage, resampled linearly, and thresholded at 0.5.
LENS_MASK_SUPERSAMPLE = 4

# --------------------------------------------------------------------------------------
# Spec
# --------------------------------------------------------------------------------------


@dataclass
class RecordingSpec:
    """All parameters of one recording.

    Initial conditions (``position``, ``orientation_wxyz``, ``velocity``,
    ``angular_velocity``; camera frame, at t = 0) left as ``None`` are drawn
    from ``seed``: a throw that rises then falls across the view, a uniformly
    random orientation and a spin of ``spin_rate`` rad/s about the principal
    axis ``spin_axis`` plus a random off-axis part of relative size
    ``spin_wobble``. Drawn specs are resampled until the object stays fully in
    view (``margin_px`` from the border) for all frames and blur sub-frames;
    fully explicit specs that leave the view are rejected (ValueError).
    """

    name: str = "tshape"
    shape: str = "tshape"  # "tshape" | "box" | "cylinder"
    width: int = 640
    height: int = 480
    fps: float = 60.0
    n_frames: int = 45
    fovy_deg: float = 40.0
    tilt_deg: float = 10.0
    roll_deg: float = 5.0
    # initial state at t = 0, camera frame (None = drawn from seed)
    position: Optional[Sequence[float]] = None  # mesh origin, m
    orientation_wxyz: Optional[Sequence[float]] = None  # of R (X_cam = R X_obj + t)
    velocity: Optional[Sequence[float]] = None  # of the mesh origin, m/s
    angular_velocity: Optional[Sequence[float]] = None  # rad/s, camera frame
    # how to draw what is None
    spin_rate: float = 10.0  # rad/s
    spin_axis: str = "major"  # "major" | "intermediate" | "minor" | "random"
    spin_wobble: float = 0.2  # off-axis fraction of the spin
    depth_range: tuple = (1.2, 1.5)  # m, start depth of the COM
    margin_px: int = 3
    max_tries: int = 200
    # object
    density: float = 600.0  # kg/m^3
    rgba: tuple = (0.58, 0.45, 0.32, 1.0)  # light wood
    # imaging
    seed: int = 0
    blur_subframes: int = 5  # renders averaged per frame (1 = no blur)
    exposure: float = 0.5  # exposure time as a fraction of the frame interval
    noise_sigma: float = 3.0 / 255.0  # Gaussian sensor noise, in [0, 1] units
    codec: str = "h264"  # "h264" (libx264 through PyAV, yuv420p like a phone), "h264_444" (yuv444p: colour
    # at full resolution), "h264rgb" or an OpenCV fourcc
    crf: int = 14  # H.264 constant rate factor (lower = better; phones record at roughly 14-20)
    # how the stored values encode the light: "linear" stores the render's values as they are
    # (the blur's sub-frames, the noise and the pixels' partial coverage mixed in them, as before);
    # "srgb" / "bt709" take the render's values as light, sum them as a sensor does and store
    # the sum through that curve (torchfit.video.TRANSFERS; SegmentationSettings.transfer reads it)
    transfer: str = "linear"
    shadows: bool = False
    scene_seed: int = 0  # background texture
    # a plain wall and floor (their textures' mean colours and fine grain alone) and no cabinet or
    # crate: a background with little for a registration of the camera's motion to hold on to
    plain_scene: bool = False
    # physics
    timestep: float = 1.0 / 4000.0
    fluid: bool = False  # MuJoCo's ellipsoid fluid model (off = vacuum)
    fluid_density: float = 1.204  # kg/m^3 (air)
    fluid_viscosity: float = 1.81e-5  # Pa s (air)
    # --- hidden effects (issue 6); the defaults reproduce the recordings made before them ---
    ball_radius: float = 0.033  # m, shape "sphere" (an icosphere, the same in mesh.obj and MuJoCo)
    # MuJoCo ellipsoid-model coefficients (blunt drag, slender drag, angular drag, Kutta lift,
    # Magnus lift); None = MuJoCo's defaults (0.5, 0.25, 1.5, 1.0, 1.0)
    fluidcoef: Optional[Sequence[float]] = None
    # put the fluid forces on an invisible, massless sphere at the centre of mass whose
    # cross-section is the mesh's reference area (hull area / 4), instead of on the visible
    # geoms: aerodynamics that are exactly torchfit's isotropic quadratic_drag + magnus
    fluid_sphere: bool = False
    # a hidden dense block inside the object: (centre (3,) in mesh coordinates, half sizes (3,),
    # mass kg); mesh.obj stays the visible uniform shape, the simulated body is heavier off-centre
    hidden_weight: Optional[tuple] = None
    fps_stated: Optional[float] = None  # frame rate written in the video container (None = fps)
    distortion: Optional[Sequence[float]] = None  # (k1, k2) radial, left out of camera.json
    # rolling shutter: row y exposed at t + line_delay (y - cy), seconds per row; drawn in bands of
    # shutter_band rows, each from the flight at its centre row's time (the object's rows only:
    # the background does not move)
    line_delay: Optional[float] = None
    shutter_band: int = 4
    # where drawn throws start / end horizontally, fractions of the width
    u_start: tuple = (0.2, 0.3)
    u_end: tuple = (0.7, 0.8)
    write_effects: bool = False  # write truth["effects"] (the hidden effects; {} = none)
    # checks
    min_iou: float = 0.95

    def replace(self, **kw) -> "RecordingSpec":
        return dataclasses.replace(self, **kw)


_HIDDEN_FIELDS = ("ball_radius", "fluidcoef", "fluid_sphere", "hidden_weight", "fps_stated",
                  "distortion", "u_start", "u_end", "write_effects", "line_delay", "shutter_band")
_SPEC_DEFAULTS = {f.name: f.default for f in dataclasses.fields(RecordingSpec)}
MJ_FLUIDCOEF = (0.5, 0.25, 1.5, 1.0, 1.0)  # MuJoCo's defaults: blunt, slender, angular, Kutta, Magnus
AIR_DENSITY = 1.2  # kg/m^3, torchfit.effects.AIR_DENSITY: the density the effects assume


def fluid_truth(spec: RecordingSpec, scene, mesh: trimesh.Trimesh) -> dict:
    """MuJoCo's ellipsoid-model forces on the fluid sphere, in torchfit's effect conventions.

    For a sphere of radius r (A = pi r^2 = the mesh's reference area, V = 4/3 pi r^3) MuJoCo
    (engine_passive.c, mj_viscousForces + mj_addedMassForces, ``docs: computation/fluid``) applies
    at the centre of mass, with v, w the body's velocity and angular velocity::

        F = -rho C_blunt A |v| v            (A_proj = A_max = pi r^2, the slender term vanishes)
            + rho (C_M V - m_A) (w x v)     (Magnus, plus the added-mass term (m_A v) x w; the
                                             -m_A dv/dt part is left out by MuJoCo; m_A = V/2)
            - 6 pi r beta v                 (Stokes)
        tau = -rho C_ang (8 pi / 15) r^5 |w| w - 8 pi r^3 beta w

    torchfit: quadratic_drag F = -1/2 rho C_d A |v| v, magnus F = 1/2 rho C_L A r (w x v), so
    C_d = 2 C_blunt and C_L = 2 (C_M V - m_A) / (A r), both for rho = AIR_DENSITY (1.2).
    """
    g = next(g for g in range(scene.model.ngeom) if scene.model.geom_bodyid[g] == scene.body
             and scene.model.geom_group[g] >= 3 and scene.model.geom_type[g] == 2)  # mjGEOM_SPHERE
    r = float(scene.model.geom_size[g, 0])
    fl = np.asarray(scene.model.geom_fluid[g], float)  # interaction, 5 coefficients, m_A (3), I_A (3)
    blunt, slender, angular, kutta, magnus = (float(c) for c in fl[1:6])
    area, volume, m_added = math.pi * r * r, 4.0 / 3.0 * math.pi * r ** 3, float(fl[6])
    rho, beta = float(spec.fluid_density), float(spec.fluid_viscosity)
    scale = rho / AIR_DENSITY
    return {
        "model": "MuJoCo ellipsoid fluid model on an invisible massless sphere at the centre of mass",
        "sphere_radius_m": r, "reference_area_m2": area, "volume_m3": volume,
        "fluid_density": rho, "fluid_viscosity": beta,
        "fluidcoef": {"blunt_drag": blunt, "slender_drag": slender, "angular_drag": angular,
                      "kutta_lift": kutta, "magnus_lift": magnus},
        "added_mass_volume_m3": m_added,
        "drag_coefficient": 2.0 * blunt * scale,
        "lift_coefficient": 2.0 * (magnus * volume - m_added) / (area * r) * scale,
        "linear_damping_kg_s": 6.0 * math.pi * r * beta,
        "spin_damping_linear_N_m_s": 8.0 * math.pi * r ** 3 * beta,
        "spin_damping_quadratic_N_m_s2": rho * angular * 8.0 * math.pi / 15.0 * r ** 5,
        "torchfit_air_density": AIR_DENSITY,
    }


def hidden_effects(spec: RecordingSpec, scene, mesh: trimesh.Trimesh) -> dict:
    """{vocabulary name: {parameter: value}} of what the recording hides ({} = nothing).

    Parameter names are torchfit's (``torchfit.effects.EFFECTS[name].null_params``), so
    ``make_effect(name, area=shape.reference_area, **params)`` rebuilds each one.
    """
    out = {}
    if spec.fluid:
        if not spec.fluid_sphere:
            raise ValueError(f"{spec.name}: effects truth needs fluid_sphere=True (the ellipsoid "
                             "model on the visible geoms has no exact torchfit counterpart)")
        fl = fluid_truth(spec, scene, mesh)
        if fl["drag_coefficient"] != 0.0:
            out["quadratic_drag"] = {"drag_coefficient": fl["drag_coefficient"]}
        if abs(fl["lift_coefficient"]) > 1e-3:  # C_M = 1/2 cancels the added-mass lift (to ~1e-6)
            out["magnus"] = {"lift_coefficient": fl["lift_coefficient"]}
        if fl["linear_damping_kg_s"] > 0:
            out["linear_drag"] = {"damping": fl["linear_damping_kg_s"]}
        if fl["spin_damping_linear_N_m_s"] > 0 or fl["spin_damping_quadratic_N_m_s2"] > 0:
            raise ValueError(f"{spec.name}: spin damping (viscosity or angular drag) has no exact "
                             "torchfit counterpart here; set fluid_viscosity=0 and fluidcoef[2]=0")
    if spec.hidden_weight is not None:
        nominal = Scene(spec.replace(hidden_weight=None), mesh)
        out["com_offset"] = {"offset": _lst(scene.com - nominal.com, 12)}
    if spec.fps_stated is not None:
        out["time_scale"] = {"time_scale": float(spec.fps) / float(spec.fps_stated)}
    if spec.distortion is not None:
        out["lens_distortion"] = {"k1": float(spec.distortion[0]), "k2": float(spec.distortion[1])}
    if spec.line_delay is not None:
        out["rolling_shutter"] = {"line_delay": float(spec.line_delay)}
    return out


def shipped_specs() -> list[RecordingSpec]:
    """The recordings shipped in torchfit/recordings."""
    return [
        # main: T-handle, tumbling mostly about its major (stable) axis, plus some
        RecordingSpec(name="tshape", shape="tshape", spin_rate=10.0, spin_axis="major",
                      spin_wobble=0.35, tilt_deg=10.0, roll_deg=5.0, seed=1),
        # spin about the intermediate axis: the Dzhanibekov flip happens within the clip
        RecordingSpec(name="tshape_intermediate", shape="tshape", spin_rate=15.0,
                      spin_axis="intermediate", spin_wobble=0.1, tilt_deg=8.0,
                      roll_deg=-4.0, seed=2),
        RecordingSpec(name="box_fast", shape="box", spin_rate=20.0, spin_axis="random",
                      tilt_deg=12.0, roll_deg=3.0, seed=3),
        RecordingSpec(name="cylinder", shape="cylinder", spin_rate=3.0, spin_axis="random",
                      tilt_deg=6.0, roll_deg=-6.0, depth_range=(1.5, 1.8), seed=4),
        # small, for fast unit tests; a short (daylight) shutter, 1/300 s: at 160x120 or with
        # 1/60 s the blurred band is wider than the 5 px arm and IoU stays below 0.9
        RecordingSpec(name="tshape_small", shape="tshape", width=320, height=240, fps=30.0,
                      n_frames=12, fovy_deg=40.0, depth_range=(0.9, 1.0),
                      spin_rate=9.0, spin_axis="major", spin_wobble=0.3,
                      tilt_deg=10.0, roll_deg=5.0, exposure=0.1, seed=5),
    ]


# --------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------


def make_mesh(shape: str, ball_radius: float = 0.033) -> trimesh.Trimesh:
    """The object's mesh, in its own (mesh.obj) coordinates, metres."""
    if shape == "sphere":
        return trimesh.creation.icosphere(subdivisions=3, radius=float(ball_radius))
    if shape == "tshape":
        bar = trimesh.creation.box(extents=(0.20, 0.03, 0.03))
        stem = trimesh.creation.box(extents=(0.03, 0.15, 0.03))
        stem.apply_translation((0.0, 0.015 + 0.075, 0.0))
        return trimesh.util.concatenate([bar, stem])
    if shape == "box":
        return trimesh.creation.box(extents=(0.12, 0.08, 0.05))
    if shape == "cylinder":
        return trimesh.creation.cylinder(radius=0.035, height=0.22, sections=32)
    raise ValueError(f"unknown shape {shape!r}")


def camera_intrinsics(width: int, height: int, fovy_deg: float) -> dict:
    fy = (height / 2.0) / math.tan(math.radians(fovy_deg) / 2.0)
    return {"fx": fy, "fy": fy, "cx": (width - 1) / 2.0, "cy": (height - 1) / 2.0,
            "width": int(width), "height": int(height)}


def gravity_dir(tilt_deg: float, roll_deg: float) -> np.ndarray:
    t, r = math.radians(tilt_deg), math.radians(roll_deg)
    return np.array([math.sin(r) * math.cos(t), math.cos(r) * math.cos(t), math.sin(t)])


def camera_rotation(tilt_deg: float, roll_deg: float) -> np.ndarray:
    """R_cw: MuJoCo world (z up, gravity -z) -> OpenCV camera, X_c = R_cw (X_w - p_cam).

    Columns are the world axes expressed in camera coordinates: world z (up) = -d,
    world x = camera x made horizontal, world y = z x x.
    """
    d = gravity_dir(tilt_deg, roll_deg)
    ez = -d
    ex = np.array([1.0, 0.0, 0.0]) - ez[0] * ez
    ex /= np.linalg.norm(ex)
    ey = np.cross(ez, ex)
    return np.stack([ex, ey, ez], axis=1)


def quat_to_mat(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def mat_to_quat(R) -> np.ndarray:
    """(w, x, y, z) with w >= 0."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(R)).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def random_quat(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def distort_normalised(xy: np.ndarray, distortion) -> np.ndarray:
    """(N,2) normalised coordinates -> distorted, x_d = x (1 + k1 r^2 + k2 r^4)."""
    k1, k2 = (float(k) for k in distortion)
    r2 = (xy * xy).sum(-1, keepdims=True)
    return xy * (1.0 + k1 * r2 + k2 * r2 * r2)


def undistort_normalised(xy_d: np.ndarray, distortion, iterations: int = 50) -> np.ndarray:
    """Inverse of :func:`distort_normalised` (fixed-point iteration; exact to ~1e-12 here)."""
    xy = xy_d.copy()
    k1, k2 = (float(k) for k in distortion)
    for _ in range(iterations):
        r2 = (xy * xy).sum(-1, keepdims=True)
        xy = xy_d / (1.0 + k1 * r2 + k2 * r2 * r2)
    return xy


def project(points_cam: np.ndarray, cam: dict, distortion=None) -> np.ndarray:
    """(N,3) camera-frame points -> (N,2) pixel coordinates (OpenCV convention).

    ``distortion`` (k1, k2): radial distortion applied to the normalised coordinates.
    """
    z = points_cam[:, 2]
    if distortion is not None:
        xy = distort_normalised(points_cam[:, :2] / z[:, None], distortion)
        return np.stack([cam["fx"] * xy[:, 0] + cam["cx"], cam["fy"] * xy[:, 1] + cam["cy"]], axis=1)
    return np.stack([cam["fx"] * points_cam[:, 0] / z + cam["cx"],
                     cam["fy"] * points_cam[:, 1] / z + cam["cy"]], axis=1)


def render_silhouette(vertices: np.ndarray, faces: np.ndarray, R: np.ndarray,
                      t: np.ndarray, cam: dict, supersample: int = 31,
                      distortion=None) -> np.ndarray:
    """Binary silhouette of a mesh at pose (R, t): numpy projection + cv2.fillConvexPoly.

    A pixel is "in" when its centre is inside the projected mesh (OpenGL's
    rasterisation rule). cv2's fill rounds vertices to whole pixels and includes the
    boundary (a ~0.5 px dilation, too much for small objects), so the triangles are
    filled at ``supersample`` (odd) times the resolution over the object's bounding
    box, and the supersampled pixel at each pixel's centre is read back. Every
    triangle is filled on its own, so their union is taken.
    """
    H, W = cam["height"], cam["width"]
    pc = vertices @ np.asarray(R).T + np.asarray(t)
    if np.any(pc[:, 2] <= 1e-6):
        raise ValueError("mesh behind the camera")
    uv = project(pc, cam, distortion)
    out = np.zeros((H, W), bool)
    x0, y0 = max(int(np.floor(uv[:, 0].min())) - 1, 0), max(int(np.floor(uv[:, 1].min())) - 1, 0)
    x1, y1 = min(int(np.ceil(uv[:, 0].max())) + 1, W - 1), min(int(np.ceil(uv[:, 1].max())) + 1, H - 1)
    if x1 < x0 or y1 < y0:
        return out
    S = int(supersample) | 1
    # pixel centre (x, y) -> supersampled pixel ((x - x0) * S + S // 2, ...)
    hi = (uv - [x0, y0]) * S + S // 2
    img = np.zeros(((y1 - y0 + 1) * S, (x1 - x0 + 1) * S), np.uint8)
    pts = np.round(hi * 16.0).astype(np.int32)
    for f in faces:
        cv2.fillConvexPoly(img, pts[f], 1, lineType=cv2.LINE_8, shift=4)
    out[y0:y1 + 1, x0:x1 + 1] = img[S // 2::S, S // 2::S].astype(bool)
    return out


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    u = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / u) if u else 1.0


def check_ground_truth(mesh: trimesh.Trimesh, cam: dict, Rs, ts, masks,
                       distortion=None, shutter_poses=None) -> np.ndarray:
    """IoU per frame between the projected mesh at the true poses and the true masks.

    With ``distortion`` the mesh is first cut into <= 5 mm triangles (straight edges bend). With
    ``shutter_poses`` (per frame, ``(first row, end row, R, t)`` of each rolling-shutter band the
    object reaches) those rows are drawn from their band's pose.
    """
    if distortion is not None:
        V, F = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, 0.005)
    else:
        V, F = mesh.vertices, mesh.faces
    V = np.asarray(V, float)
    F = np.asarray(F)
    ious = []
    for i, (R, t, m) in enumerate(zip(Rs, ts, masks)):
        drawn = render_silhouette(V, F, R, t, cam, distortion=distortion)
        for first, end, R_band, t_band in (shutter_poses[i] if shutter_poses is not None else ()):
            drawn[first:end] = render_silhouette(V, F, R_band, t_band, cam)[first:end]
        ious.append(mask_iou(drawn, m))
    return np.array(ious)


def mask_bbox(m: np.ndarray) -> list:
    ys, xs = np.nonzero(m)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    return [int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())]


# --------------------------------------------------------------------------------------
# MuJoCo scene
# --------------------------------------------------------------------------------------

CAM_HEIGHT = 2.0  # camera height above the floor (world z), m
WALL_DIST = 5.0  # horizontal distance from the camera to the back wall, m


def _noise_field(rng, h, w, scale):
    """Smooth random field in [0,1] (upsampled Gaussian noise)."""
    small = rng.normal(size=(max(2, h // scale), max(2, w // scale))).astype(np.float32)
    f = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    f = cv2.GaussianBlur(f, (0, 0), scale / 2.0)
    f -= f.min()
    return f / max(f.max(), 1e-6)


def _textures(scene_seed: int, plain: bool = False) -> dict:
    """Procedural background textures (PNG bytes, MuJoCo asset dict); ``plain``: the wall and the
    floor each of its mean colour and fine grain alone (:attr:`RecordingSpec.plain_scene`)."""
    rng = np.random.default_rng(1000 + scene_seed)
    out = {}
    # back wall: pale blue-grey plaster, a few posters / a window-like panel, fine grain
    h, w = 512, 1024
    n = _noise_field(rng, h, w, 64)[..., None]
    wall = (0.70 + 0.08 * n) * np.array([0.78, 0.84, 0.92], np.float32)  # RGB
    for col in ([0.75, 0.22, 0.18], [0.20, 0.45, 0.70], [0.25, 0.55, 0.30], [0.85, 0.70, 0.20],
                [0.30, 0.30, 0.35]):
        ph, pw = rng.integers(60, 170), rng.integers(50, 160)
        y0, x0 = rng.integers(40, h - ph - 40), rng.integers(20, w - pw - 20)
        inner = _noise_field(rng, ph, pw, 16)[..., None]
        wall[y0:y0 + ph, x0:x0 + pw] = np.array(col, np.float32) * (0.75 + 0.35 * inner)
        wall[y0:y0 + ph, x0:x0 + 3] *= 0.5
        wall[y0:y0 + 3, x0:x0 + pw] *= 0.5
    if plain:
        wall = np.broadcast_to(wall.mean((0, 1)), wall.shape).copy()
    wall += rng.normal(scale=0.015, size=wall.shape).astype(np.float32)
    out["wall.png"] = wall
    # floor: grey / sand tiles with noise
    h = w = 512
    yy, xx = np.mgrid[0:h, 0:w]
    chk = (((yy // 64) + (xx // 64)) % 2).astype(np.float32)[..., None]
    n = _noise_field(rng, h, w, 32)[..., None]
    floor = (chk * np.array([0.55, 0.52, 0.46]) + (1 - chk) * np.array([0.36, 0.37, 0.40]))
    floor = floor * (0.85 + 0.25 * n)
    if plain:
        floor = np.broadcast_to(floor.mean((0, 1)), floor.shape)
    floor = floor + rng.normal(scale=0.02, size=(h, w, 3))
    out["floor.png"] = floor.astype(np.float32)
    # cabinet: dark green painted wood
    h, w = 256, 256
    n = _noise_field(rng, h, w, 8)[..., None]
    cab = np.array([0.16, 0.32, 0.24]) * (0.8 + 0.4 * n)
    out["cabinet.png"] = cab.astype(np.float32)
    res = {}
    for k, img in out.items():
        bgr = np.clip(img[..., ::-1] * 255.0, 0, 255).astype(np.uint8)
        ok, buf = cv2.imencode(".png", bgr)
        assert ok
        res[k] = buf.tobytes()
    return res


def _v(a) -> str:
    return " ".join(f"{float(x):.10g}" for x in a)


def fluid_sphere_radius(mesh: trimesh.Trimesh) -> float:
    """Radius whose disc has the mesh's reference area (convex hull area / 4, as torchfit)."""
    return math.sqrt(float(mesh.convex_hull.area) / 4.0 / math.pi)


def true_com(spec: RecordingSpec, mesh: trimesh.Trimesh) -> np.ndarray:
    """Centre of mass of the simulated body (uniform mesh plus any hidden weight), mesh frame."""
    m = mesh.copy()
    m.density = float(spec.density)
    if spec.hidden_weight is None:
        return np.asarray(m.center_mass, float)
    centre, _, mw = spec.hidden_weight
    return (m.mass * np.asarray(m.center_mass) + float(mw) * np.asarray(centre, float)) / (m.mass + float(mw))


def render_geometry(spec: RecordingSpec):
    """(width, height, fovy_deg) of MuJoCo's render: the output's own without distortion; with
    it, a larger canvas of the same focal length that covers the undistorted field of view."""
    if spec.distortion is None:
        return spec.width, spec.height, spec.fovy_deg
    cam = camera_intrinsics(spec.width, spec.height, spec.fovy_deg)
    W, H, f = spec.width, spec.height, cam["fy"]
    u = np.arange(W, dtype=float)
    v = np.arange(H, dtype=float)
    border = np.concatenate([np.stack([u, np.zeros(W)], 1), np.stack([u, np.full(W, H - 1.0)], 1),
                             np.stack([np.zeros(H), v], 1), np.stack([np.full(H, W - 1.0), v], 1)])
    xy = undistort_normalised((border - [cam["cx"], cam["cy"]]) / f, spec.distortion)
    pad_x = max(0, math.ceil(np.abs(xy[:, 0]).max() * f - (W - 1) / 2.0) + 3)
    pad_y = max(0, math.ceil(np.abs(xy[:, 1]).max() * f - (H - 1) / 2.0) + 3)
    Wr, Hr = W + 2 * pad_x, H + 2 * pad_y
    return Wr, Hr, math.degrees(2.0 * math.atan((Hr / 2.0) / f))


def distortion_maps(spec: RecordingSpec):
    """cv2.remap maps (H, W) float32: output (distorted) pixel -> pixel of the wide render."""
    cam = camera_intrinsics(spec.width, spec.height, spec.fovy_deg)
    Wr, Hr, _ = render_geometry(spec)
    f = cam["fy"]
    vv, uu = np.mgrid[0:spec.height, 0:spec.width].astype(float)
    xy_d = np.stack([(uu - cam["cx"]) / f, (vv - cam["cy"]) / f], -1).reshape(-1, 2)
    xy = undistort_normalised(xy_d, spec.distortion).reshape(spec.height, spec.width, 2)
    map_x = (f * xy[..., 0] + (Wr - 1) / 2.0).astype(np.float32)
    map_y = (f * xy[..., 1] + (Hr - 1) / 2.0).astype(np.float32)
    return map_x, map_y


def build_model_xml(spec: RecordingSpec, mesh: trimesh.Trimesh, R_cw: np.ndarray):
    """MJCF text and assets. The object body frame = mesh.obj frame."""
    R_wc = R_cw.T
    p_cam = np.array([0.0, 0.0, CAM_HEIGHT])
    # MuJoCo camera axes in world: x = OpenCV x, y = -OpenCV y (up), looks along -z.
    cam_x, cam_y = R_wc[:, 0], -R_wc[:, 1]
    fwd = R_wc[:, 2].copy()
    fwd[2] = 0.0
    fwd /= np.linalg.norm(fwd)
    left = np.cross([0, 0, 1.0], fwd)
    yaw = math.degrees(math.atan2(fwd[1], fwd[0]))

    if spec.shape == "tshape":
        geoms = ('<geom name="obj0" type="box" size="0.1 0.015 0.015" pos="0 0 0" material="obj"/>'
                 '<geom name="obj1" type="box" size="0.015 0.075 0.015" pos="0 0.09 0" material="obj"/>')
        mesh_asset = ""
    elif spec.shape == "box":
        geoms = '<geom name="obj0" type="box" size="0.06 0.04 0.025" material="obj"/>'
        mesh_asset = ""
    elif spec.shape in ("cylinder", "sphere"):
        # the very same 32-gon prism (icosphere) as mesh.obj: exact (polyhedral) inertia and
        # silhouette
        geoms = '<geom name="obj0" type="mesh" mesh="objmesh" material="obj"/>'
        mesh_asset = (f'<mesh name="objmesh" inertia="exact" vertex="{_v(mesh.vertices.ravel())}" '
                      f'face="{" ".join(str(int(i)) for i in mesh.faces.ravel())}"/>')
    else:
        raise ValueError(spec.shape)
    coef = f' fluidcoef="{_v(spec.fluidcoef)}"' if spec.fluidcoef is not None else ""
    if spec.fluid and spec.fluid_sphere:
        # invisible (group 3, transparent), massless: only the fluid forces come from it
        geoms += (f'<geom name="fluid" type="sphere" size="{fluid_sphere_radius(mesh):.10g}" '
                  f'pos="{_v(true_com(spec, mesh))}" density="0" group="3" rgba="0 0 0 0" '
                  f'fluidshape="ellipsoid"{coef}/>')
    elif spec.fluid:
        geoms = geoms.replace('material="obj"', f'material="obj" fluidshape="ellipsoid"{coef}')
    if spec.fluid:
        opt_fluid = f'density="{spec.fluid_density}" viscosity="{spec.fluid_viscosity}"'
    else:
        opt_fluid = 'density="0" viscosity="0"'
    if spec.hidden_weight is not None:
        centre, half, mass = spec.hidden_weight
        geoms += (f'<geom name="weight" type="box" size="{_v(half)}" pos="{_v(centre)}" '
                  f'mass="{float(mass):.10g}" group="3" rgba="0 0 0 0"/>')

    wall_c = p_cam + WALL_DIST * fwd
    wall_c[2] = 4.0
    cab_c = p_cam + (WALL_DIST - 0.5) * fwd - 1.6 * left
    cab_c[2] = 0.6
    cab2_c = p_cam + (WALL_DIST - 0.35) * fwd + 2.2 * left
    cab2_c[2] = 0.45
    light_dir = -(fwd * 0.5 + left * 0.3 + np.array([0, 0, 1.0]))
    shadow = "true" if spec.shadows else "false"
    W, H, fovy = render_geometry(spec)
    props = "" if spec.plain_scene else f"""<geom name="cabinet" type="box" size="0.3 0.5 0.6" pos="{_v(cab_c)}"
          euler="0 0 {math.radians(yaw):.10g}" material="cabinet" density="0"/>
    <geom name="crate" type="box" size="0.3 0.3 0.45" pos="{_v(cab2_c)}"
          euler="0 0 {math.radians(yaw + 20):.10g}" material="cabinet"
          rgba="0.9 0.75 0.6 1" density="0"/>"""
    # the buffer holds the supersampled true-mask render through a lens (LENS_MASK_SUPERSAMPLE)
    W, H = (W, H) if spec.distortion is None else (LENS_MASK_SUPERSAMPLE * W, LENS_MASK_SUPERSAMPLE * H)
    xml = f"""
<mujoco model="throw_{spec.name}">
  <compiler angle="radian" alignfree="false"/>
  <option timestep="{spec.timestep:.10g}" integrator="RK4" gravity="0 0 {-G}" {opt_fluid}>
    <flag contact="disable"/>
  </option>
  <visual>
    <global offwidth="{max(W, 64)}" offheight="{max(H, 64)}"/>
    <headlight ambient="0.25 0.25 0.25" diffuse="0.35 0.35 0.35" specular="0.05 0.05 0.05"/>
    <map znear="0.01" zfar="50"/>
    <quality shadowsize="2048"/>
  </visual>
  <statistic extent="5" center="0 0 1"/>
  <default>
    <geom contype="0" conaffinity="0" density="{spec.density:.10g}"/>
  </default>
  <asset>
    <texture name="wall" type="2d" file="wall.png"/>
    <texture name="floor" type="2d" file="floor.png"/>
    <texture name="cabinet" type="2d" file="cabinet.png"/>
    <material name="wall" texture="wall" texrepeat="0.3 0.6" texuniform="true" specular="0.05" shininess="0.1"/>
    <material name="floor" texture="floor" texrepeat="0.5 0.5" texuniform="true" specular="0.1"/>
    <material name="cabinet" texture="cabinet" specular="0.2" shininess="0.3"/>
    <material name="obj" rgba="{_v(spec.rgba)}" specular="0.3" shininess="0.4" reflectance="0"/>
    {mesh_asset}
  </asset>
  <worldbody>
    <light name="key" directional="true" dir="{_v(light_dir)}" diffuse="0.55 0.55 0.52"
           specular="0.2 0.2 0.2" castshadow="{shadow}"/>
    <light name="fill" directional="true" dir="{_v(-fwd + np.array([0, 0, -0.5]))}"
           diffuse="0.2 0.2 0.22" specular="0 0 0" castshadow="false"/>
    <camera name="cam" mode="fixed" pos="{_v(p_cam)}" xyaxes="{_v(cam_x)} {_v(cam_y)}"
            fovy="{fovy:.10g}"/>
    <geom name="floor" type="box" size="12 12 0.05" pos="{_v(p_cam[:2])} -0.05"
          material="floor" density="0"/>
    <geom name="wall" type="box" size="12 4 0.05" pos="{_v(wall_c)}"
          xyaxes="{_v(-left)} 0 0 1" material="wall" density="0"/>
    {props}
    <body name="object">
      <freejoint name="free"/>
      {geoms}
    </body>
  </worldbody>
</mujoco>
"""
    return xml, _textures(spec.scene_seed, spec.plain_scene), p_cam


def offscreen_gl() -> str:
    """Choose MuJoCo's CPU offscreen backend before mujoco is imported, and return it.

    A set ``MUJOCO_GL`` is kept; otherwise OSMesa where its library is installed, else EGL (Mesa's
    software EGL, on machines without OSMesa: it renders the same masks, checked on a concealed
    recording in experiments/discover/HISTORY.md, 2026-11-25).
    """
    import ctypes.util

    if "MUJOCO_GL" not in os.environ:
        has_egl = ctypes.util.find_library("OSMesa") is None and ctypes.util.find_library("EGL") is not None
        os.environ["MUJOCO_GL"] = "egl" if has_egl else "osmesa"
    return os.environ["MUJOCO_GL"]


class Scene:
    """Compiled MuJoCo model plus the world<->camera transforms."""

    def __init__(self, spec: RecordingSpec, mesh: trimesh.Trimesh):
        offscreen_gl()  # offscreen, CPU; honours a set value
        import mujoco

        self.mj = mujoco
        self.spec = spec
        self.R_cw = camera_rotation(spec.tilt_deg, spec.roll_deg)
        self.R_wc = self.R_cw.T
        xml, assets, self.p_cam = build_model_xml(spec, mesh, self.R_cw)
        self.model = mujoco.MjModel.from_xml_string(xml, assets)
        self.data = mujoco.MjData(self.model)
        self.body = self.model.body("object").id
        self.obj_geoms = np.array([g for g in range(self.model.ngeom)  # visible ones only
                                   if self.model.geom_bodyid[g] == self.body
                                   and self.model.geom_group[g] < 3])
        self.cam = camera_intrinsics(spec.width, spec.height, spec.fovy_deg)
        m, b = self.model, self.body
        self.mass = float(m.body_mass[b])
        self.com = np.array(m.body_ipos[b])  # in body = mesh coordinates
        Ri = quat_to_mat(m.body_iquat[b])
        self.inertia = Ri @ np.diag(m.body_inertia[b]) @ Ri.T  # about COM, mesh axes

    # ---- state conversions (camera frame <-> MuJoCo world / free joint) ----
    def set_state_cam(self, p, q, v, w):
        """Set the free joint from a camera-frame state of the mesh origin."""
        Rc = quat_to_mat(q)
        Rw = self.R_wc @ Rc
        d = self.data
        d.qpos[:3] = self.p_cam + self.R_wc @ np.asarray(p, float)
        d.qpos[3:7] = mat_to_quat(Rw)
        d.qvel[:3] = self.R_wc @ np.asarray(v, float)  # world-frame velocity of body origin
        d.qvel[3:6] = Rc.T @ np.asarray(w, float)  # body-frame angular velocity
        d.time = 0.0
        self.mj.mj_forward(self.model, d)

    def state_cam(self):
        """(t, R, v, w) of the mesh in the camera frame from the current data."""
        d = self.data
        Rw = quat_to_mat(d.qpos[3:7])
        t = self.R_cw @ (d.qpos[:3] - self.p_cam)
        R = self.R_cw @ Rw
        v = self.R_cw @ d.qvel[:3]
        w = R @ d.qvel[3:6]
        return t, R, v, w

    def advance_to(self, t_target: float):
        m, d = self.model, self.data
        while d.time < t_target - 1e-12:
            m.opt.timestep = min(self.spec.timestep, t_target - d.time)
            self.mj.mj_step(m, d)
        m.opt.timestep = self.spec.timestep

    def simulate(self, ic, times):
        """qpos at each time (sorted ascending, may start < 0), from the state at t = 0.

        Times before 0 are reached by time reversal (negate velocities, integrate,
        negate back), exact for the conservative free flight (gravity + Euler's
        equations); with ``fluid`` on, the few ms before 0 neglect the fluid forces.
        """
        times = np.asarray(times, float)
        self.set_state_cam(*ic)
        t0 = float(min(times.min(), 0.0))
        if t0 < 0:
            self.data.qvel[:] *= -1.0
            self.advance_to(-t0)
            self.data.qvel[:] *= -1.0
            self.data.time = t0
        out = np.zeros((len(times), 7))
        for i, t in enumerate(times):
            self.advance_to(t)
            out[i] = self.data.qpos
        return out

    def pose_cam(self, qpos):
        Rw = quat_to_mat(qpos[3:7])
        return self.R_cw @ Rw, self.R_cw @ (qpos[:3] - self.p_cam)


# --------------------------------------------------------------------------------------
# Initial conditions
# --------------------------------------------------------------------------------------


def object_mask(seg: np.ndarray, scene: "Scene") -> np.ndarray:
    """(H, W) bool pixels of the thrown object in a (H, W, 2) MuJoCo segmentation render."""
    return (seg[..., 1] == MJ_OBJ_GEOM) & np.isin(seg[..., 0], scene.obj_geoms)


def principal_axes(inertia: np.ndarray):
    """(moments ascending, axes as columns): minor, intermediate, major."""
    evals, evecs = np.linalg.eigh(inertia)
    return evals, evecs


def sample_ic(spec: RecordingSpec, scene: Scene, rng: np.random.Generator):
    cam = scene.cam
    W, H = spec.width, spec.height
    d = gravity_dir(spec.tilt_deg, spec.roll_deg)
    T = (spec.n_frames - 1) / spec.fps
    q = np.asarray(spec.orientation_wxyz, float) if spec.orientation_wxyz is not None \
        else random_quat(rng)
    q = q / np.linalg.norm(q)
    R0 = quat_to_mat(q)
    if spec.angular_velocity is not None:
        w = np.asarray(spec.angular_velocity, float)
    else:
        _, axes = principal_axes(scene.inertia)
        if spec.spin_axis == "random":
            a = rng.normal(size=3)
        else:
            a = axes[:, {"minor": 0, "intermediate": 1, "major": 2}[spec.spin_axis]].copy()
            a *= rng.choice([-1.0, 1.0])
            perp = rng.normal(size=3)
            perp -= perp.dot(a) * a
            a = a + spec.spin_wobble * perp / np.linalg.norm(perp)
        w = R0 @ (spec.spin_rate * a / np.linalg.norm(a))
    com_off = R0 @ scene.com  # origin -> COM, camera frame
    if spec.position is not None:
        p = np.asarray(spec.position, float)
    else:
        z0 = rng.uniform(*spec.depth_range)
        z1 = z0 + rng.uniform(-0.3, 0.3)
        u0, u1 = W * rng.uniform(*spec.u_start), W * rng.uniform(*spec.u_end)
        if rng.random() < 0.5:
            u0, u1 = W - 1 - u0, W - 1 - u1
        v0, v1 = H * rng.uniform(0.6, 0.74), H * rng.uniform(0.55, 0.74)
        c0 = z0 * np.array([(u0 - cam["cx"]) / cam["fx"], (v0 - cam["cy"]) / cam["fy"], 1.0])
        c1 = z1 * np.array([(u1 - cam["cx"]) / cam["fx"], (v1 - cam["cy"]) / cam["fy"], 1.0])
        p = c0 - com_off
    if spec.velocity is not None:
        v = np.asarray(spec.velocity, float)
    else:
        if spec.position is not None:  # aim: same depth, mirror across the view
            c0 = p + com_off
            c1 = c0 * np.array([-1.0, 1.0, 1.0])
        v_com = (c1 - c0) / T - 0.5 * G * d * T
        v = v_com - np.cross(w, com_off)  # velocity of the mesh origin
    return p, q, v, w


class VideoWriter:
    """Writes RGB uint8 frames: H.264 through PyAV (``codec="h264"``: libx264, yuv420p like a phone;
    ``"h264_444"``: libx264 with colour at full resolution; ``"h264rgb"``: libx264rgb on the RGB
    frames, lossless at crf 0) or any OpenCV fourcc."""

    H264 = {"h264": ("libx264", "yuv420p", "slow"), "h264_444": ("libx264", "yuv444p", "slow"),
            "h264rgb": ("libx264rgb", "rgb24", "ultrafast")}

    def __init__(self, path: Path, spec: RecordingSpec, width: int, height: int):
        self.container = self.stream = self.cv_writer = None
        if spec.codec in self.H264:
            import av  # the `recordings` extra

            encoder, pix_fmt, preset = self.H264[spec.codec]
            self.container = av.open(str(path), "w")
            fps = spec.fps if spec.fps_stated is None else spec.fps_stated  # what the file says
            self.stream = self.container.add_stream(encoder, rate=Fraction(fps).limit_denominator(1001))
            self.stream.width, self.stream.height, self.stream.pix_fmt = width, height, pix_fmt
            self.stream.options = {"crf": str(int(spec.crf)), "preset": preset}
            if spec.transfer != "linear":  # name the curve in the stream, as a camera does (H.273 codes)
                self.stream.codec_context.color_trc = {"bt709": 1, "srgb": 13}[spec.transfer]
        else:
            self.cv_writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*spec.codec),
                                             float(spec.fps if spec.fps_stated is None
                                                   else spec.fps_stated), (width, height))
            if not self.cv_writer.isOpened():
                raise RuntimeError(f"cv2.VideoWriter failed to open codec {spec.codec!r}")

    def write(self, rgb: np.ndarray) -> None:
        if self.cv_writer is not None:
            self.cv_writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            return
        import av

        for packet in self.stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")):
            self.container.mux(packet)

    def release(self) -> None:
        if self.cv_writer is not None:
            self.cv_writer.release()
            return
        for packet in self.stream.encode():
            self.container.mux(packet)
        self.container.close()


def encode(light: np.ndarray, transfer: str) -> np.ndarray:
    """Light on a 0..255 scale stored through the camera curve ``transfer`` (0..255, not
    rounded); the inverse of ``torchfit.video._decode``."""
    if transfer == "linear":
        return light
    x = np.clip(light / 255.0, 0.0, 1.0)
    if transfer == "srgb":
        return 255.0 * np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    if transfer == "bt709":
        return 255.0 * np.where(x < 0.018, 4.5 * x, 1.099 * x**0.45 - 0.099)
    raise ValueError(f"transfer must be linear, srgb or bt709, got {transfer!r}")


def sample_times(spec: RecordingSpec):
    """Frame times and, per frame, the blur sub-frame times (centred on the frame)."""
    tf = np.arange(spec.n_frames) / spec.fps
    K = max(1, int(spec.blur_subframes))
    if K == 1:
        offs = np.zeros(1)
    else:
        offs = (np.arange(K) / (K - 1) - 0.5) * spec.exposure / spec.fps
    return tf, tf[:, None] + offs[None, :]


def shutter_bands(spec: RecordingSpec) -> list[tuple[int, int, float]]:
    """A rolling shutter's row bands ``(first row, end row, seconds after the frame time)``, the
    offset at the band's centre row; [] without one."""
    if spec.line_delay is None:
        return []
    if spec.distortion is not None:
        raise ValueError(f"{spec.name}: a rolling shutter with lens distortion is not supported")
    cy = (spec.height - 1) / 2.0
    step = int(spec.shutter_band)
    return [(r, min(r + step, spec.height), float(spec.line_delay) * ((r + min(r + step, spec.height) - 1) / 2 - cy))
            for r in range(0, spec.height, step)]


def all_times(spec: RecordingSpec) -> np.ndarray:
    """Every time the recording samples the flight: frames, blur sub-frames and shutter bands."""
    tf, ts = sample_times(spec)
    base = np.concatenate([tf, ts.ravel()])
    offsets = [b[2] for b in shutter_bands(spec)]
    return np.unique(np.concatenate([base] + [base + o for o in offsets]))


def in_view(scene: Scene, mesh: trimesh.Trimesh, qpos_all, margin: int):
    cam = scene.cam
    V = np.asarray(mesh.vertices)
    for qp in qpos_all:
        R, t = scene.pose_cam(qp)
        pc = V @ R.T + t
        if pc[:, 2].min() < 0.3 or pc[:, 2].max() > 3.5:
            return False
        uv = project(pc, cam, scene.spec.distortion)
        if (uv[:, 0].min() < margin or uv[:, 1].min() < margin
                or uv[:, 0].max() > cam["width"] - 1 - margin
                or uv[:, 1].max() > cam["height"] - 1 - margin):
            return False
        if (scene.p_cam + scene.R_wc @ pc.T.mean(1))[2] < 0.3:  # well above the floor
            return False
    return True


def resolve_ic(spec: RecordingSpec, scene: Scene, mesh: trimesh.Trimesh):
    rng = np.random.default_rng(spec.seed)
    times = all_times(spec)
    explicit = all(x is not None for x in (spec.position, spec.orientation_wxyz,
                                           spec.velocity, spec.angular_velocity))
    for attempt in range(1 if explicit else spec.max_tries):
        ic = sample_ic(spec, scene, rng)
        qpos = scene.simulate(ic, times)
        if in_view(scene, mesh, qpos, spec.margin_px):
            return ic, attempt
    if explicit:
        raise ValueError(f"{spec.name}: the object leaves the view (or touches the border)")
    raise RuntimeError(f"{spec.name}: no in-view throw found in {spec.max_tries} tries")


# --------------------------------------------------------------------------------------
# Recording
# --------------------------------------------------------------------------------------


def _lst(a, nd=9):
    return np.round(np.asarray(a, float), nd).tolist() if nd else np.asarray(a, float).tolist()


def make_recording(spec: RecordingSpec, out_dir, verbose: bool = True) -> dict:
    """Make OUT_DIR/spec.name/{video.mp4, camera.json, mesh.obj, truth.json, masks.npz}.

    Returns a summary dict (paths, IoU figures). Raises if the ground-truth check fails.
    """
    t_start = time.time()
    mesh = make_mesh(spec.shape, spec.ball_radius)
    scene = Scene(spec, mesh)
    mj, model, data = scene.mj, scene.model, scene.data
    cam = scene.cam
    ic, n_rejected = resolve_ic(spec, scene, mesh)

    tf, ts = sample_times(spec)
    K = ts.shape[1]
    times = all_times(spec)
    qpos = scene.simulate(ic, times)
    idx = {float(t): i for i, t in enumerate(times)}
    bands = shutter_bands(spec)
    V_obj = np.asarray(mesh.vertices)

    # state at t = 0 read back from MuJoCo (sanity: equals the ic)
    scene.set_state_cam(*ic)
    p0, R0, v0, w0 = scene.state_cam()

    H, W = spec.height, spec.width
    Wr, Hr, _ = render_geometry(spec)
    maps = distortion_maps(spec) if spec.distortion is not None else None
    renderer = mj.Renderer(model, Hr, Wr)
    S = LENS_MASK_SUPERSAMPLE
    fine = mj.Renderer(model, S * Hr, S * Wr) if maps is not None else None
    if fine is not None:  # renders nothing but the true masks
        fine.enable_segmentation_rendering()
    rng = np.random.default_rng(10_000 + spec.seed)
    out = Path(out_dir) / spec.name
    out.mkdir(parents=True, exist_ok=True)
    writer = VideoWriter(out / "video.mp4", spec, W, H)

    def set_qpos(qp):
        data.qpos[:] = qp
        data.qvel[:] = 0.0
        mj.mj_forward(model, data)

    def object_bands(R, t):
        """The shutter bands the object can reach in a frame where its pose is (R, t): its rows
        then (projected mesh) with a margin for the motion within the readout."""
        if not bands:
            return []
        rows = project(V_obj @ R.T + t, cam)[:, 1]
        low, high = rows.min() - 40, rows.max() + 40
        return [b for b in bands if b[1] > low and b[0] < high]

    masks = np.zeros((spec.n_frames, H, W), bool)
    Rs, tvecs, shutter_poses = [], [], []
    try:
        for i in range(spec.n_frames):
            qp = qpos[idx[float(tf[i])]]  # the frame's time
            R, t = scene.pose_cam(qp)
            # blurred, noisy colour frame
            acc = np.zeros((Hr, Wr, 3), np.float64)
            renderer.disable_segmentation_rendering()
            for k in range(K):
                set_qpos(qpos[idx[float(ts[i, k])]])
                renderer.update_scene(data, camera="cam")
                acc += renderer.render()
            reached = object_bands(R, t)
            for first, end, offset in reached:  # the object's rows, each band at its own time
                band = np.zeros((end - first, Wr, 3), np.float64)
                for k in range(K):
                    set_qpos(qpos[idx[float(ts[i, k] + offset)]])
                    renderer.update_scene(data, camera="cam")
                    band += renderer.render()[first:end]
                acc[first:end] = band
            if maps is not None:  # through the lens: the wide pinhole render, distorted
                acc = cv2.remap(acc.astype(np.float32), maps[0], maps[1], cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
            img = acc / K + rng.normal(scale=spec.noise_sigma * 255.0, size=acc.shape)
            img = np.clip(np.round(encode(img, spec.transfer)), 0, 255).astype(np.uint8)
            writer.write(img)
            # true mask + pose at the frame time
            set_qpos(qp)
            if maps is None:
                renderer.enable_segmentation_rendering()
                renderer.update_scene(data, camera="cam")
                masks[i] = object_mask(renderer.render(), scene)
            else:  # supersampled coverage, resampled linearly (LENS_MASK_SUPERSAMPLE)
                fine.update_scene(data, camera="cam")
                cover = object_mask(fine.render(), scene).reshape(Hr, S, Wr, S).mean((1, 3), dtype=np.float32)
                masks[i] = cv2.remap(cover, maps[0], maps[1], cv2.INTER_LINEAR) >= 0.5
            poses = []
            for first, end, offset in reached:
                band_qpos = qpos[idx[float(tf[i] + offset)]]
                set_qpos(band_qpos)
                renderer.update_scene(data, camera="cam")
                masks[i, first:end] = object_mask(renderer.render(), scene)[first:end]
                poses.append((first, end, *scene.pose_cam(band_qpos)))
            shutter_poses.append(poses)
            Rs.append(R)
            tvecs.append(t)
    finally:
        writer.release()
        renderer.close()
        if fine is not None:
            fine.close()

    # --- independent check: projected mesh.obj vs MuJoCo's segmentation ---
    mesh.export(out / "mesh.obj")
    mesh_back = trimesh.load(out / "mesh.obj", force="mesh", process=False)
    ious = check_ground_truth(mesh_back, cam, Rs, tvecs, masks, spec.distortion, shutter_poses if bands else None)
    ok = bool(ious.min() >= spec.min_iou)
    if not all(m.any() for m in masks):
        ok = False

    # orientation quaternions, sign-continuous from frame to frame, w >= 0 at frame 0
    quats = []
    for R in Rs:
        q = mat_to_quat(R)
        if quats and np.dot(q, quats[-1]) < 0:
            q = -q
        quats.append(q)

    d = gravity_dir(spec.tilt_deg, spec.roll_deg)
    truth = {
        "fps": float(spec.fps),
        "g": G,
        "gravity_dir": _lst(d, 12),
        "tilt_deg": float(spec.tilt_deg),
        "roll_deg": float(spec.roll_deg),
        "shape": spec.shape,
        "object": {
            "mesh": "mesh.obj",
            "density": float(spec.density),
            "mass": float(scene.mass),
            "com": _lst(scene.com, 12),
            "inertia": _lst(scene.inertia, 15),
        },
        "params": {
            "position": _lst(p0, 12),
            "orientation_wxyz": _lst(mat_to_quat(R0), 12),
            "R": _lst(R0, 12),
            "velocity": _lst(v0, 12),
            "angular_velocity": _lst(w0, 12),
        },
        "per_frame": {
            "frame": list(range(spec.n_frames)),
            "time": _lst(tf, 12),
            "position": _lst(tvecs, 12),
            "orientation_wxyz": _lst(quats, 12),
            "R": _lst(Rs, 12),
            "bbox": [mask_bbox(m) for m in masks],
        },
        "masks": "masks.npz",
        "render": {
            "blur_subframes": int(K),
            "exposure_frac": float(spec.exposure),
            "noise_sigma": float(spec.noise_sigma),
            "transfer": spec.transfer,
            "codec": (f"h264 ({', '.join(VideoWriter.H264[spec.codec][:2])}, crf {spec.crf})"
                      if spec.codec in VideoWriter.H264 else spec.codec),
            "engine": f"MuJoCo {mj.__version__} (physics RK4 dt={spec.timestep:g}, OpenGL render)",
            "fluid": bool(spec.fluid),
            "fluid_density": float(spec.fluid_density) if spec.fluid else 0.0,
            "fluid_viscosity": float(spec.fluid_viscosity) if spec.fluid else 0.0,
        },
        "check": {"iou_min": float(ious.min()), "iou_median": float(np.median(ious))},
        "spec": {k: (list(v) if isinstance(v, tuple) else v)
                 for k, v in dataclasses.asdict(spec).items()
                 if not (k in _HIDDEN_FIELDS and v == _SPEC_DEFAULTS[k])},
    }
    # hidden effects: keys only written when used, so older recordings regenerate unchanged
    if spec.hidden_weight is not None:  # "object" = what mesh.obj at the density gives
        nominal = Scene(spec.replace(hidden_weight=None), mesh)
        truth["object"].update(mass=float(nominal.mass), com=_lst(nominal.com, 12),
                               inertia=_lst(nominal.inertia, 15))
        truth["hidden_weight"] = {
            "centre": _lst(spec.hidden_weight[0], 12), "half_size": _lst(spec.hidden_weight[1], 12),
            "mass": float(spec.hidden_weight[2]),
            "body_mass": float(scene.mass), "body_com": _lst(scene.com, 12),
            "body_inertia": _lst(scene.inertia, 15),
            "principal_moment_ratio": _lst(np.linalg.eigvalsh(scene.inertia)
                                           / np.linalg.eigvalsh(nominal.inertia), 9),
        }
    if spec.fps_stated is not None:
        truth.update(fps_true=float(spec.fps), fps_stated=float(spec.fps_stated))
    if spec.distortion is not None:
        truth["camera_true"] = dict(cam, dist_coeffs=[float(spec.distortion[0]),
                                                      float(spec.distortion[1]), 0.0, 0.0, 0.0])
        truth["render"]["canvas"] = list(render_geometry(spec))
    if spec.fluid and spec.fluid_sphere:
        truth["fluid_model"] = fluid_truth(spec, scene, mesh)
    if spec.write_effects:
        truth["effects"] = hidden_effects(spec, scene, mesh)
    with open(out / "camera.json", "w") as f:
        json.dump(cam, f, indent=1)
    with open(out / "truth.json", "w") as f:
        json.dump(truth, f, indent=1)
    np.savez_compressed(out / "masks.npz", masks=masks)

    summary = {
        "name": spec.name, "dir": str(out), "iou_median": float(np.median(ious)),
        "iou_min": float(ious.min()), "ok": ok, "rejected_throws": n_rejected,
        "seconds": time.time() - t_start,
        "sizes": {p.name: p.stat().st_size for p in sorted(out.iterdir())},
    }
    if verbose:
        print(f"[{spec.name}] IoU median {summary['iou_median']:.4f} worst {summary['iou_min']:.4f}"
              f"  |w|={np.linalg.norm(w0):.1f} rad/s  rejected throws {n_rejected}"
              f"  {summary['seconds']:.1f}s  "
              f"{sum(summary['sizes'].values()) / 1024:.0f} KB", flush=True)
    if not ok:
        raise AssertionError(f"{spec.name}: ground-truth check failed, IoU per frame {ious}")
    return summary


# --------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------


def _parse_spec_args(items: Sequence[str]) -> dict:
    kw = {}
    names = {f.name for f in dataclasses.fields(RecordingSpec)}
    for it in items:
        if "=" not in it:
            raise SystemExit(f"--spec expects key=value, got {it!r}")
        k, v = it.split("=", 1)
        if k not in names:
            raise SystemExit(f"unknown spec field {k!r}; fields: {sorted(names)}")
        try:
            kw[k] = ast.literal_eval(v)
        except (ValueError, SyntaxError):
            kw[k] = v  # plain string
    return kw


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="torchfit/recordings", help="output folder")
    ap.add_argument("--only", action="append", default=[],
                    help="make only this shipped recording (repeatable, or comma-separated)")
    ap.add_argument("--spec", nargs="+", metavar="KEY=VALUE",
                    help="make one custom recording: RecordingSpec fields, e.g. "
                         "name=mine shape=box spin_rate=5.0 position='(0.1,0.2,2.0)'")
    ap.add_argument("--list", action="store_true", help="list the shipped specs and exit")
    args = ap.parse_args(argv)
    offscreen_gl()

    if args.list:
        for s in shipped_specs():
            print(s)
        return 0
    if args.spec:
        specs = [RecordingSpec(**_parse_spec_args(args.spec))]
    else:
        specs = shipped_specs()
        only = {n for o in args.only for n in o.split(",") if n}
        if only:
            unknown = only - {s.name for s in specs}
            if unknown:
                raise SystemExit(f"unknown recording(s) {sorted(unknown)}")
            specs = [s for s in specs if s.name in only]
    total = 0
    for s in specs:
        total += sum(make_recording(s, args.out)["sizes"].values())
    print(f"done: {len(specs)} recording(s) in {args.out}, {total / 1024:.0f} KB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
