"""Experiment 3 of the paper (Fig. 6): camera tilt and roll from the motion alone, and the
video rectified so that gravity points straight down.

The fit recovers gravity's direction in the camera frame together with the motion; its two
angles are the camera's tilt and roll (:func:`torchfit.camera.tilt_roll_from_direction`). The
rectifying homography ``K R K⁻¹`` (:func:`torchfit.camera.rectifying_homography`) turns the
camera about its centre until gravity is the image's +y axis; a uniform scale and a shift
(which keep "down" down) then fit the whole warped frame into the original size.

The recordings are made at run time by the MuJoCo generator of the repository
(``experiments/recordings/make_recordings.py``, extra ``[recordings]``), one per camera roll;
``quick=True`` uses the shipped ``tshape_small`` recording and the quick search instead.

Outputs in ``out_dir``: ``fig6_roll.png`` (each recording's original frame with its gravity
arrows and centroid track, and the rectified frame), ``errors.png`` (tilt and roll errors per
recording), ``<name>/rectified.mp4`` per recording, ``summary.json``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from collections.abc import Callable, Sequence
from importlib import resources
from pathlib import Path

import numpy as np
import torch

from ..camera import Camera, rectifying_homography, tilt_roll_from_direction
from ..search import SearchSettings
from ..shape import load_shape
from ..video import read_frames

__all__ = [
    "angle_difference_deg",
    "canvas_similarity",
    "gravity_free_residual",
    "gravity_image_direction",
    "load_generator",
    "main",
    "slant_deg",
    "warp_points",
]

REPO_GENERATOR = Path(__file__).resolve().parents[2] / "experiments" / "recordings"
DEFAULT_ROLLS = (-20.0, -8.0, 0.0, 12.0, 25.0)
DEFAULT_TILTS = (8.0, 15.0, 5.0, 12.0, 10.0)
DEFAULT_SHAPES = ("tshape", "box", "tshape", "cylinder", "tshape")


# ---------------------------------------------------------------------------------------------
# geometry


def angle_difference_deg(estimate: float, truth: float) -> float:
    """Signed ``estimate - truth`` in degrees, wrapped to (-180, 180]."""
    diff = (float(estimate) - float(truth)) % 360.0
    return diff - 360.0 if diff > 180.0 else diff


def warp_points(homography: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (3, 3) homography to (N, 2) pixel coordinates; returns (N, 2)."""
    points = np.asarray(points, float)
    homogeneous = np.concatenate((points, np.ones((len(points), 1))), 1) @ np.asarray(homography, float).T
    return homogeneous[:, :2] / homogeneous[:, 2:3]


def canvas_similarity(homography: np.ndarray, width: int, height: int) -> np.ndarray:
    """(3, 3) scale-and-shift that fits the warped image frame into ``width × height``.

    No rotation, so a direction that ``homography`` maps to straight down stays straight down.
    The scale is at most 1 (a rectified frame is never enlarged).

    Raises:
        ValueError: a corner maps to infinity or behind the camera (a rotation of 90° or more).
    """
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]])
    homogeneous = np.concatenate((corners, np.ones((4, 1))), 1) @ np.asarray(homography, float).T
    if not np.all(homogeneous[:, 2] > 1e-9):
        raise ValueError("the rectifying rotation turns part of the image behind the camera; "
                         f"corner depths {homogeneous[:, 2].round(3).tolist()}")
    warped = homogeneous[:, :2] / homogeneous[:, 2:3]
    low, high = warped.min(0), warped.max(0)
    scale = min(1.0, width / (high[0] - low[0]), height / (high[1] - low[1]))
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    shift = centre - scale * (low + high) / 2.0
    return np.array([[scale, 0.0, shift[0]], [0.0, scale, shift[1]], [0.0, 0.0, 1.0]])


def gravity_image_direction(camera: Camera, direction: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Unit image direction in which a point at each pixel moves when it moves along gravity.

    The derivative of the projection of ``X + s d`` at ``s = 0`` is, up to a positive factor
    ``1 / Z``, ``(fx d_x - (u - c_x) d_z, fy d_y - (v - c_y) d_z)``: the same for every depth.

    Args:
        camera: intrinsics.
        direction: (3,) gravity direction, camera frame.
        pixels: (N, 2) pixel positions.

    Returns:
        (N, 2) unit image directions (+y is down the image).
    """
    d = np.asarray(direction, float)
    pixels = np.asarray(pixels, float)
    step = np.stack((camera.fx * d[0] - (pixels[:, 0] - camera.cx) * d[2],
                     camera.fy * d[1] - (pixels[:, 1] - camera.cy) * d[2]), -1)
    return step / np.linalg.norm(step, axis=-1, keepdims=True)


def slant_deg(directions: np.ndarray) -> np.ndarray:
    """Angle of (N, 2) image directions from straight down (+y), degrees, positive toward +x."""
    directions = np.asarray(directions, float)
    return np.degrees(np.arctan2(directions[:, 0], directions[:, 1]))


def gravity_free_residual(times: np.ndarray, u: np.ndarray) -> float:
    """RMS residual (pixels) of a coordinate fitted by ``(a + b t) / (1 + c t)``.

    In a view whose image x axis is perpendicular to gravity, a centre of mass in free flight
    has ``u = fx (X₀ + V_x t) / (Z₀ + V_z t) + c_x`` (no gravity term): this model. In a rolled
    view gravity's quadratic leaks into ``u`` and the residual grows.

    Args:
        times: (T,) seconds.
        u: (T,) pixel coordinate (the one that should be free of gravity).
    """
    times, u = np.asarray(times, float), np.asarray(u, float)
    if len(times) < 4:
        raise ValueError(f"need at least 4 points for the 3-parameter fit, got {len(times)}")
    design = np.stack((np.ones_like(times), times, -times * u), -1)  # u (1 + c t) = a + b t
    (a, b, c), *_ = np.linalg.lstsq(design, u, rcond=None)
    model = (a + b * times) / (1.0 + c * times)
    return float(np.sqrt(np.mean((u - model) ** 2)))


# ---------------------------------------------------------------------------------------------
# recordings


def load_generator(folder: str | Path | None = None):
    """The repository's MuJoCo recording generator (``make_recordings``), imported from
    ``folder`` (default: ``experiments/recordings`` of this checkout).

    Raises:
        RuntimeError: the script, MuJoCo or PyAV is missing (one line saying what to do).
    """
    folder = Path(folder) if folder else REPO_GENERATOR
    script = folder / "make_recordings.py"
    hint = ("paper_roll makes its recordings with MuJoCo: it needs experiments/recordings/make_recordings.py "
            "from a clone of the repository and `pip install -e '.[recordings]'` (mujoco, av); "
            "or run params.quick=true")
    if not script.is_file():
        raise RuntimeError(f"{hint} (no generator at {script})")
    try:
        import av  # noqa: F401
        import mujoco  # noqa: F401
    except ImportError as err:
        raise RuntimeError(f"{hint} ({err})") from None
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))
    import make_recordings

    return make_recordings


def _spec_json(spec) -> dict:
    return json.loads(json.dumps({k: (list(v) if isinstance(v, tuple) else v)
                                  for k, v in dataclasses.asdict(spec).items()}))


def _make_recordings(out: Path, rolls, tilts, shapes, *, width, height, fps, n_frames, seed,
                     generator, progress) -> list[Path]:
    """One recording per roll in ``out``; a folder whose truth.json has the same spec is reused."""
    mr = load_generator(generator)
    folders = []
    for i, (roll, tilt, shape) in enumerate(zip(rolls, tilts, shapes)):
        name = f"roll{i}_{shape}_{'m' if roll < 0 else 'p'}{abs(roll):g}"
        spec = mr.RecordingSpec(name=name, shape=shape, width=width, height=height, fps=fps, n_frames=n_frames,
                                tilt_deg=float(tilt), roll_deg=float(roll), spin_rate=8.0 + 2.0 * (i % 3),
                                spin_axis="random", seed=7000 + 100 * seed + i, scene_seed=i % 4)
        folder = out / name
        truth = folder / "truth.json"
        if truth.is_file() and json.loads(truth.read_text()).get("spec") == _spec_json(spec):
            progress(f"{name}: reusing the recording in {folder}")
        else:
            mr.make_recording(spec, out, verbose=False)
            progress(f"{name}: made a {width}x{height} recording, tilt {tilt:g}°, roll {roll:g}°")
        folders.append(folder)
    return folders


def _quick_settings(seed: int) -> SearchSettings:
    import yaml

    values = yaml.safe_load(resources.files("torchfit").joinpath("configs/search/quick.yaml").read_text())
    return SearchSettings(**(values | {"seed": seed}))


# ---------------------------------------------------------------------------------------------
# one recording


def _analyse(folder: Path, out: Path, settings: SearchSettings, *, device, dtype, progress,
             write_video: bool) -> dict:
    """Fit one recording, compare tilt and roll with the truth, rectify its video."""
    from ..run import fit_recording  # run.py imports the task modules

    truth = json.loads((folder / "truth.json").read_text())
    camera = Camera.from_file(folder / "camera.json")
    shape = load_shape(folder / "mesh.obj", density=float(truth["object"]["density"]))
    fitted = fit_recording(folder / "video.mp4", shape, camera, settings, truth=folder / "truth.json",
                           dtype=dtype, device=device, progress=progress)
    direction = fitted.result.candidates.gravity(1.0)[0].detach().double().cpu()
    direction = (direction / direction.norm()).numpy()
    tilt, roll = (math.degrees(float(a)) for a in tilt_roll_from_direction(torch.from_numpy(direction)))
    true_dir = np.asarray(truth["gravity_dir"], float)
    true_tilt, true_roll = float(truth["tilt_deg"]), float(truth["roll_deg"])
    track = fitted.result.track

    homography = rectifying_homography(camera, math.radians(tilt), math.radians(roll))
    canvas = canvas_similarity(homography, camera.width, camera.height)

    # the silhouettes' centroids over the fitted span: data the rectification did not see
    span = fitted.span
    used = fitted.observation.used[span]
    masks = fitted.observation.masks[span][used]
    rows, cols = np.indices(masks.shape[1:])
    area = masks.sum((1, 2))
    centroids = np.stack(((masks * cols).sum((1, 2)) / area, (masks * rows).sum((1, 2)) / area), -1)
    times = (span[used] - span[0]) / fitted.observation.fps
    rectified = warp_points(homography, centroids)

    # true verticals (lines along the true gravity) at the object's true positions, after the fit's rectification
    positions = np.asarray(truth["per_frame"]["position"], float)[span]
    on_image = positions[:, :2] / positions[:, 2:3] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    rotation = np.linalg.inv(camera.K) @ homography @ camera.K  # the rectifying rotation
    slants = slant_deg(gravity_image_direction(camera, rotation @ true_dir, warp_points(homography, on_image)))

    video = None
    if write_video:
        video = out / "rectified.mp4"
        _write_rectified(folder / "video.mp4", canvas @ homography, camera, fitted.observation.fps, video)
    frame = int(span[len(span) // 2])
    picture = read_frames(folder / "video.mp4", [frame])[0]
    return {
        "name": folder.name,
        "shape": truth["shape"],
        "size": [camera.width, camera.height],
        "frames": len(span),
        "true_tilt_deg": true_tilt,
        "true_roll_deg": true_roll,
        "tilt_deg": tilt,
        "roll_deg": roll,
        "tilt_error_deg": angle_difference_deg(tilt, true_tilt),
        "roll_error_deg": angle_difference_deg(roll, true_roll),
        "gravity_error_deg": float(fitted.truth["gravity_error_deg"]),
        "track_tilt_error_deg": angle_difference_deg(math.degrees(track["tilt"]), true_tilt),
        "track_roll_error_deg": angle_difference_deg(math.degrees(track["roll"]), true_roll),
        "rotation_error_deg": float(fitted.truth["rotation_error_deg"]),
        "position_error_pct_depth": float(fitted.truth["position_error_pct_depth"]),
        "max_true_vertical_slant_deg": float(np.abs(slants).max()),
        "centroid_x_residual_original_px": gravity_free_residual(times, centroids[:, 0]),
        "centroid_x_residual_rectified_px": gravity_free_residual(times, rectified[:, 0]),
        "fit_s": float(fitted.timing["fit_s"]),
        "video": f"{out.name}/{video.name}" if video else None,
        # for the figure (dropped from the summary)
        "_picture": picture,
        "_frame_centroid": centroids[min(len(centroids) - 1, int(np.searchsorted(span[used], frame)))],
        "_centroids": centroids,
        "_direction": direction,
        "_true_direction": true_dir,
        "_homography": canvas @ homography,
        "_camera": camera,
    }


def _write_rectified(video: Path, homography: np.ndarray, camera: Camera, fps: float, path: Path) -> None:
    import cv2

    frames = read_frames(video, range(_frame_count(video)))
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (camera.width, camera.height))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV could not open {path} for writing (mp4v)")
    try:
        for rgb in frames:
            warped = cv2.warpPerspective(rgb, homography, (camera.width, camera.height), flags=cv2.INTER_LINEAR)
            writer.write(cv2.cvtColor(warped, cv2.COLOR_RGB2BGR))
    finally:
        writer.release()


def _frame_count(video: Path) -> int:
    import cv2

    capture = cv2.VideoCapture(str(video))
    try:
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    finally:
        capture.release()
    if count <= 0:
        raise ValueError(f"could not count the frames of {video}")
    return count


# ---------------------------------------------------------------------------------------------
# figures


def _arrow(ax, start, direction, length, color) -> None:
    """True gravity in white, drawn wider, so that the fitted red arrow on top leaves it visible."""
    width = 4.5 if color == "white" else 1.8
    ax.annotate("", xy=tuple(start + length * direction), xytext=tuple(start),
                arrowprops={"arrowstyle": "-|>", "lw": width, "mutation_scale": 10 + 3 * width, "color": color})


def _figure_rectification(rows: list[dict], path: Path) -> None:
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(rows), 2, figsize=(8.0, 3.0 * len(rows)), squeeze=False)
    for row, (left, right) in zip(rows, axes):
        camera = row["_camera"]
        size = (camera.width, camera.height)
        length = 0.25 * camera.height
        point = row["_frame_centroid"][None]
        left.imshow(row["_picture"])
        left.plot(*row["_centroids"].T, ".", color="yellow", ms=3)
        for direction, color in ((row["_true_direction"], "white"), (row["_direction"], "red")):
            _arrow(left, point[0], gravity_image_direction(camera, direction, point)[0], length, color)
        left.set_title(f"{row['name']}: original (roll {row['true_roll_deg']:g}°, tilt {row['true_tilt_deg']:g}°)",
                       fontsize=8)
        homography = row["_homography"]
        right.imshow(cv2.warpPerspective(row["_picture"], homography, size, flags=cv2.INTER_LINEAR))
        warped = warp_points(homography, row["_centroids"])
        right.plot(*warped.T, ".", color="yellow", ms=3)
        start = warp_points(homography, point)
        # the image of a short step along each gravity direction, through the warp
        for direction, color in ((row["_true_direction"], "white"), (row["_direction"], "red")):
            end = warp_points(homography, point + 1e-3 * gravity_image_direction(camera, direction, point))
            step = (end - start)[0]
            _arrow(right, start[0], step / np.linalg.norm(step), length, color)
        right.set_title(f"rectified (fit: roll {row['roll_deg']:.2f}°, tilt {row['tilt_deg']:.2f}°)", fontsize=8)
        for ax in (left, right):
            ax.set_xlim(-0.5, camera.width - 0.5)
            ax.set_ylim(camera.height - 0.5, -0.5)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle("Gravity from the motion alone (red: fitted, white: true; yellow: silhouette centroids)",
                 fontsize=9)
    fig.tight_layout()
    _save_small_png(fig, path, dpi=90)
    plt.close(fig)


def _save_small_png(fig, path: Path, dpi: int) -> None:
    """Photographs with sensor noise compress badly: keep a 128-colour palette (a quarter the size)."""
    import io

    from PIL import Image

    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=dpi, format="png")
    buffer.seek(0)
    with Image.open(buffer) as image:
        image.convert("RGB").quantize(colors=128, method=Image.Quantize.MEDIANCUT).save(path, optimize=True)


def _figure_errors(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [f"{r['shape']}\nroll {r['true_roll_deg']:g}°\ntilt {r['true_tilt_deg']:g}°" for r in rows]
    x = np.arange(len(rows))
    fig, axes = plt.subplots(1, 2, figsize=(max(6.0, 1.6 * len(rows) + 2.5), 3.4), sharey=True)
    for ax, key in zip(axes, ("roll", "tilt")):
        fit = [abs(r[f"{key}_error_deg"]) for r in rows]
        track = [abs(r[f"track_{key}_error_deg"]) for r in rows]
        ax.bar(x - 0.2, track, 0.4, color="0.7", label="centroid parabola (search stage 1)")
        ax.bar(x + 0.2, fit, 0.4, color="tab:red", label="silhouette fit (result)")
        for xi, value in zip(x, fit):
            ax.text(xi + 0.2, value, f"{value:.2f}", ha="center", va="bottom", fontsize=7)
        ax.set_xticks(x, names, fontsize=7)
        ax.set_title(f"|{key} error|", fontsize=9)
        ax.set_yscale("log")
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_ylabel("degrees")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------


def main(out_dir: str | Path, *, quick: bool = False, device="cpu", dtype: torch.dtype = torch.float32,
         progress: Callable[[str], None] = print, seed: int = 0,
         rolls_deg: Sequence[float] = DEFAULT_ROLLS, tilts_deg: Sequence[float] = DEFAULT_TILTS,
         shapes: Sequence[str] = DEFAULT_SHAPES, width: int = 320, height: int = 240, fps: float = 60.0,
         n_frames: int = 45, generator: str | None = None, videos: bool = True) -> dict:
    """Recover tilt and roll over several recordings, rectify them, write figures and summary.json.

    Args:
        out_dir: output folder (recordings go to ``out_dir/recordings``).
        quick: the shipped ``tshape_small`` recording and the quick search (no MuJoCo).
        rolls_deg, tilts_deg, shapes: one recording each, same lengths.
        width, height, fps, n_frames: the recordings' size, rate and length.
        generator: folder holding ``make_recordings.py`` (default: this checkout's).
        videos: write ``<name>/rectified.mp4``.

    Returns:
        The summary (also ``summary.json``): per recording tilt/roll truth, fit and errors.

    Raises:
        ValueError: lists of different lengths, or an empty list.
        RuntimeError: MuJoCo or the generator missing (full mode only).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if quick:
        folders = [Path(str(resources.files("torchfit").joinpath("recordings/tshape_small")))]
        settings = _quick_settings(seed)
    else:
        if not (len(rolls_deg) == len(tilts_deg) == len(shapes) >= 1):
            raise ValueError(f"rolls_deg, tilts_deg and shapes need one entry per recording, got "
                             f"{len(rolls_deg)}, {len(tilts_deg)} and {len(shapes)}")
        folders = _make_recordings(out_dir / "recordings", rolls_deg, tilts_deg, shapes, width=width,
                                   height=height, fps=fps, n_frames=n_frames, seed=seed,
                                   generator=generator, progress=progress)
        settings = SearchSettings(seed=seed)
    rows = []
    for folder in folders:
        row = _analyse(folder, out_dir / folder.name, settings, device=device, dtype=dtype, progress=progress,
                       write_video=videos)
        progress(f"{row['name']}: roll {row['roll_deg']:.2f}° (true {row['true_roll_deg']:g}°), "
                 f"tilt {row['tilt_deg']:.2f}° (true {row['true_tilt_deg']:g}°), fit {row['fit_s']:.0f} s")
        rows.append(row)
    _figure_rectification(rows, out_dir / "fig6_roll.png")
    _figure_errors(rows, out_dir / "errors.png")
    table = [{k: v for k, v in row.items() if not k.startswith("_")} for row in rows]
    roll_errors = np.abs([r["roll_error_deg"] for r in table])
    tilt_errors = np.abs([r["tilt_error_deg"] for r in table])
    summary = {
        "quick": bool(quick),
        "search": "quick" if quick else "default",
        "recordings": table,
        "max_abs_roll_error_deg": float(roll_errors.max()),
        "median_abs_roll_error_deg": float(np.median(roll_errors)),
        "max_abs_tilt_error_deg": float(tilt_errors.max()),
        "median_abs_tilt_error_deg": float(np.median(tilt_errors)),
        "figures": ["fig6_roll.png", "errors.png"],
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary
