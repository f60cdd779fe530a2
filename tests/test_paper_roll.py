"""Paper experiment 3 (camera roll from gravity): rectification geometry, errors, quick run."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module

from torchfit.camera import Camera, gravity_direction, rectifying_homography
from torchfit.paper import roll
from torchfit.run import run

CAMERA = Camera(fx=400.0, fy=410.0, cx=159.5, cy=119.5, width=320, height=240)
ANGLES = [(0.0, 0.0), (10.0, -20.0), (15.0, 25.0), (-8.0, 12.0), (5.0, -35.0)]


def _direction(tilt_deg: float, roll_deg: float) -> np.ndarray:
    return gravity_direction(torch.tensor(math.radians(tilt_deg), dtype=torch.float64),
                             torch.tensor(math.radians(roll_deg), dtype=torch.float64)).numpy()


def _project(points: np.ndarray) -> np.ndarray:
    return points[:, :2] / points[:, 2:3] * [CAMERA.fx, CAMERA.fy] + [CAMERA.cx, CAMERA.cy]


def _points(n: int = 20) -> np.ndarray:
    rng = np.random.default_rng(0)
    return np.stack((rng.uniform(-0.4, 0.4, n), rng.uniform(-0.3, 0.3, n), rng.uniform(1.0, 2.0, n)), -1)


@pytest.mark.parametrize("tilt, roll_deg", ANGLES)
def test_vertical_lines_become_vertical_and_point_down(tilt, roll_deg):
    """A 3D line along gravity images, after rectification and the canvas fit, to a vertical
    image line traversed downward (+y) — at every point of the image, not only the centre."""
    direction = _direction(tilt, roll_deg)
    homography = rectifying_homography(CAMERA, math.radians(tilt), math.radians(roll_deg))
    homography = roll.canvas_similarity(homography, CAMERA.width, CAMERA.height) @ homography
    starts = _points()
    previous = roll.warp_points(homography, _project(starts))
    for step in (0.05, 0.1, 0.2):
        current = roll.warp_points(homography, _project(starts + step * direction))
        np.testing.assert_allclose(current[:, 0], previous[:, 0], atol=1e-8)
        assert np.all(current[:, 1] > previous[:, 1])
        previous = current
    # before rectification, a rolled or tilted view does not have them vertical
    if (tilt, roll_deg) != (0.0, 0.0):
        moved = _project(starts + 0.2 * direction)[:, 0] - _project(starts)[:, 0]
        assert np.abs(moved).max() > 1.0


@pytest.mark.parametrize("tilt, roll_deg", ANGLES)
def test_canvas_keeps_the_whole_frame_and_does_not_turn(tilt, roll_deg):
    homography = rectifying_homography(CAMERA, math.radians(tilt), math.radians(roll_deg))
    canvas = roll.canvas_similarity(homography, CAMERA.width, CAMERA.height)
    assert canvas[0, 1] == canvas[1, 0] == 0.0 and canvas[0, 0] == canvas[1, 1] <= 1.0
    corners = np.array([[-0.5, -0.5], [319.5, -0.5], [319.5, 239.5], [-0.5, 239.5]])
    warped = roll.warp_points(canvas @ homography, corners)
    assert np.all(warped >= -0.5 - 1e-9) and np.all(warped[:, 0] <= 319.5 + 1e-9) and np.all(warped[:, 1] <= 239.5 + 1e-9)
    # the frame fills the canvas along one axis at least
    extent = warped.max(0) - warped.min(0)
    assert max(extent[0] / 320, extent[1] / 240) == pytest.approx(1.0) or canvas[0, 0] == 1.0


def test_canvas_rejects_a_turn_behind_the_camera():
    with pytest.raises(ValueError, match="behind the camera"):
        roll.canvas_similarity(rectifying_homography(CAMERA, math.radians(80.0), 0.0), 320, 240)


@pytest.mark.parametrize("tilt, roll_deg", ANGLES)
def test_gravity_image_direction_matches_finite_differences(tilt, roll_deg):
    direction = _direction(tilt, roll_deg)
    starts = _points()
    step = _project(starts + 1e-6 * direction) - _project(starts)
    expected = step / np.linalg.norm(step, axis=-1, keepdims=True)
    np.testing.assert_allclose(roll.gravity_image_direction(CAMERA, direction, _project(starts)), expected,
                               atol=1e-5)


@pytest.mark.parametrize("error", [-3.0, 0.5, 7.0])
def test_slant_of_true_verticals_equals_minus_the_roll_error(error):
    """Level camera, rectified with a roll off by ``error``: at the principal point true
    verticals lean by exactly ``-error`` degrees (a pure turn about the optical axis; square
    pixels, else pixel angles are not scene angles)."""
    true_roll = 12.0
    camera = Camera(fx=400.0, fy=400.0, cx=159.5, cy=119.5, width=320, height=240)
    homography = rectifying_homography(camera, 0.0, math.radians(true_roll + error))
    rotation = np.linalg.inv(camera.K) @ homography @ camera.K
    centre = np.array([[camera.cx, camera.cy]])
    slant = roll.slant_deg(roll.gravity_image_direction(camera, rotation @ _direction(0.0, true_roll), centre))
    assert slant[0] == pytest.approx(-error, abs=1e-9)


@pytest.mark.parametrize("estimate, truth, expected", [(10.0, 8.0, 2.0), (179.0, -179.0, -2.0),
                                                       (-179.0, 179.0, 2.0), (-20.5, -20.0, -0.5)])
def test_angle_difference_wraps(estimate, truth, expected):
    assert roll.angle_difference_deg(estimate, truth) == pytest.approx(expected)


def test_rectified_free_flight_has_no_gravity_in_x():
    """A centre of mass in free flight seen by a rolled camera: the horizontal image coordinate
    carries gravity's quadratic; after rectification it is the gravity-free model exactly."""
    tilt, roll_deg = 10.0, -20.0
    times = np.linspace(0.0, 0.7, 40)
    path = (np.array([-0.3, 0.1, 1.4]) + np.outer(times, [0.9, -3.0, 0.2])
            + 0.5 * 9.81 * np.outer(times**2, _direction(tilt, roll_deg)))
    pixels = _project(path)
    rectified = roll.warp_points(rectifying_homography(CAMERA, math.radians(tilt), math.radians(roll_deg)), pixels)
    assert roll.gravity_free_residual(times, rectified[:, 0]) < 1e-6
    assert roll.gravity_free_residual(times, pixels[:, 0]) > 2.0
    with pytest.raises(ValueError, match="at least 4"):
        roll.gravity_free_residual(times[:3], pixels[:3, 0])


def test_missing_generator_says_what_to_do(tmp_path):
    with pytest.raises(RuntimeError, match="make_recordings.py"):
        roll.load_generator(tmp_path)


def test_lists_of_different_lengths_are_rejected(tmp_path):
    with pytest.raises(ValueError, match="one entry per recording"):
        roll.main(tmp_path, rolls_deg=[0.0, 10.0], tilts_deg=[5.0], shapes=["tshape", "box"])


def test_quick_config_runs_and_rectifies(tmp_path):
    with initialize_config_module(config_module="torchfit.configs", version_base="1.3"):
        cfg = compose(config_name="config", overrides=["experiment=paper_roll", "params.quick=true", "quiet=true"])
    summary = run(cfg, tmp_path)
    assert json.loads((tmp_path / "summary.json").read_text()) == json.loads(json.dumps(summary))
    (row,) = summary["recordings"]
    assert row["true_roll_deg"] == 5.0 and row["true_tilt_deg"] == 10.0
    # the quick search on the 12-frame tshape_small clip: roll within a few degrees (tilt is weak there)
    assert abs(row["roll_error_deg"]) < 3.0
    assert row["roll_error_deg"] == pytest.approx(row["roll_deg"] - 5.0)
    for name in summary["figures"]:
        assert (tmp_path / name).stat().st_size > 0
    capture = cv2.VideoCapture(str(tmp_path / row["video"]))
    frames = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    size = (int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    capture.release()
    camera = json.loads((Path(__file__).resolve().parents[1] / "torchfit" / "recordings" / "tshape_small"
                         / "camera.json").read_text())
    assert frames == 12 and size == (camera["width"], camera["height"])
