import math

import numpy as np
import pytest
import torch

from torchfit.camera import (
    Camera,
    gravity_direction,
    project,
    rectifying_homography,
    rectifying_rotation,
    tilt_roll_from_direction,
)

CAM = Camera(500.0, 480.0, 319.5, 239.5, 640, 480)


def test_projection_known_values_and_shape():
    points = torch.tensor([[0.0, 0.0, 2.0], [1.0, -0.5, 2.0]]).expand(3, 4, 2, 3)  # (B, T, V, 3)
    pixels, in_front = project(CAM, points)
    assert pixels.shape == (3, 4, 2, 2) and in_front.all()
    np.testing.assert_allclose(pixels[0, 0].numpy(), [[319.5, 239.5], [319.5 + 250.0, 239.5 - 120.0]])


def test_points_behind_camera_are_flagged_and_finite():
    points = torch.tensor([[0.1, 0.1, -1.0], [0.1, 0.1, 0.0], [0.1, 0.1, 1.0]], requires_grad=True)
    pixels, in_front = project(CAM, points)
    assert in_front.tolist() == [False, False, True]
    assert torch.isfinite(pixels).all()
    pixels.sum().backward()
    assert torch.isfinite(points.grad).all()


def test_projection_gradcheck():
    points = torch.tensor([[0.1, -0.2, 1.5], [0.3, 0.2, 2.5]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p: project(CAM, p)[0], (points,))


@pytest.mark.parametrize("tilt, roll", [(0.0, 0.0), (0.2, -0.3), (-0.5, 1.0), (0.1, 3.0)])
def test_gravity_tilt_roll_roundtrip(tilt, roll):
    d = gravity_direction(torch.tensor(tilt, dtype=torch.float64), torch.tensor(roll, dtype=torch.float64))
    assert float(d.norm()) == pytest.approx(1.0)
    t2, r2 = tilt_roll_from_direction(d)
    assert float(t2) == pytest.approx(tilt, abs=1e-12)
    assert float(r2) == pytest.approx(roll, abs=1e-12)
    rect = rectifying_rotation(tilt, roll)
    np.testing.assert_allclose(rect @ d.numpy(), [0.0, 1.0, 0.0], atol=1e-12)


def test_level_camera_has_gravity_down_the_image():
    d = gravity_direction(torch.tensor(0.0), torch.tensor(0.0))
    np.testing.assert_allclose(d.numpy(), [0.0, 1.0, 0.0], atol=1e-7)
    # looking down: gravity gains a forward (+z) component
    assert float(gravity_direction(torch.tensor(0.3), torch.tensor(0.0))[2]) > 0


def test_rectifying_homography_maps_rotated_points():
    tilt, roll = 0.15, -0.25
    H = rectifying_homography(CAM, tilt, roll)
    rot = rectifying_rotation(tilt, roll)
    point = np.array([0.2, -0.1, 2.0])
    pix = CAM.K @ point
    rect = CAM.K @ (rot @ point)
    mapped = H @ pix
    np.testing.assert_allclose(mapped[:2] / mapped[2], rect[:2] / rect[2], atol=1e-9)


def test_camera_file_json_and_yaml(tmp_path):
    path = tmp_path / "cam.json"
    path.write_text('{"fx": 500, "fy": 500, "cx": 100, "cy": 80, "width": 200, "height": 160}')
    assert Camera.from_file(path).cx == 100
    import cv2

    yaml_path = tmp_path / "calib.yaml"
    storage = cv2.FileStorage(str(yaml_path), cv2.FILE_STORAGE_WRITE)
    storage.write("camera_matrix", np.array([[400.0, 0, 150], [0, 410.0, 90], [0, 0, 1]]))
    storage.write("dist_coeffs", np.array([[0.1, -0.05, 0.0, 0.0, 0.0]]))
    storage.write("image_width", 300)
    storage.write("image_height", 200)
    storage.release()
    cam = Camera.from_file(yaml_path)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (400.0, 410.0, 150.0, 90.0, 300, 200)
    assert cam.dist_coeffs[:2] == (0.1, -0.05)


@pytest.mark.parametrize("kwargs, message", [
    (dict(fx=0.0), "fx must be positive"),
    (dict(fy=-3.0), "fy must be positive"),
    (dict(cx=900.0), "principal point outside"),
    (dict(cy=-20.0), "principal point outside"),
    (dict(width=0), "width must be positive"),
    (dict(fx=math.nan), "fx must be positive"),
])
def test_bad_intrinsics_raise(kwargs, message):
    values = dict(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480) | kwargs
    with pytest.raises(ValueError, match=message):
        Camera(**values)


def test_bad_camera_files(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        Camera.from_file(tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"fx": 1}')
    with pytest.raises(ValueError, match="must be JSON with fx"):
        Camera.from_file(bad)
