"""OpenCV pinhole camera, gravity direction from (tilt, roll), and roll/pitch rectification.

The world frame is the camera frame: x right, y down, z forward; pixel (0, 0)'s centre is at
(0, 0) as in OpenCV. Gravity is ``g * d`` with

    d(tilt, roll) = (sin(roll) cos(tilt), cos(roll) cos(tilt), sin(tilt)),

so ``tilt`` is the angle between gravity and the image plane (positive when the camera looks
down) and ``roll`` the angle of gravity's image-plane projection from the image's +y axis,
positive toward +x. A level camera has ``d = (0, 1, 0)``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "Camera",
    "project",
    "gravity_direction",
    "tilt_roll_from_direction",
    "rectifying_rotation",
    "rectifying_homography",
]


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in pixels and the image size.

    Attributes:
        fx, fy: focal lengths, pixels.
        cx, cy: principal point, pixels (pixel (0, 0)'s centre is (0, 0)).
        width, height: image size, pixels.
        dist_coeffs: OpenCV distortion coefficients (k1, k2, p1, p2[, k3...]) or empty; the
            projection here is undistorted, masks are undistorted before fitting.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist_coeffs: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "width", "height"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"camera {name} must be positive, got {value!r}")
        for name, size in (("cx", self.width), ("cy", self.height)):
            value = getattr(self, name)
            if not (math.isfinite(value) and -0.5 <= value <= size - 0.5):
                raise ValueError(
                    f"camera {name} = {value!r} puts the principal point outside the image "
                    f"(expected within [-0.5, {size - 0.5}])"
                )

    @property
    def distorted(self) -> bool:
        """Whether any distortion coefficient is non-zero (images are then undistorted)."""
        return any(c != 0 for c in self.dist_coeffs)

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @staticmethod
    def from_dict(data: dict) -> "Camera":
        """A camera from a camera file's JSON content (``fx, fy, cx, cy, width, height``[,
        ``dist_coeffs``]); raises KeyError or TypeError for a missing or malformed key."""
        return Camera(
            float(data["fx"]), float(data["fy"]), float(data["cx"]), float(data["cy"]),
            int(data["width"]), int(data["height"]),
            tuple(float(c) for c in data.get("dist_coeffs", ())),
        )

    @staticmethod
    def from_file(path: str | Path) -> "Camera":
        """Read a JSON file (``fx, fy, cx, cy, width, height``[, ``dist_coeffs``]) or OpenCV's
        calibration YAML (``camera_matrix``, ``dist_coeffs``, ``image_width``, ``image_height``).

        Raises:
            ValueError: missing or unreadable file, or missing keys.
        """
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"camera file {str(path)!r} does not exist")
        if path.suffix.lower() == ".json":
            try:
                return Camera.from_dict(json.loads(path.read_text()))
            except (KeyError, TypeError, json.JSONDecodeError) as err:
                raise ValueError(
                    f"camera file {str(path)!r} must be JSON with fx, fy, cx, cy, width, height: {err}"
                ) from None
        import cv2

        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        if not storage.isOpened():
            raise ValueError(f"could not read camera file {str(path)!r} (JSON or OpenCV YAML expected)")
        try:
            matrix = storage.getNode("camera_matrix").mat()
            dist = storage.getNode("dist_coeffs").mat()
            width = storage.getNode("image_width").real()
            height = storage.getNode("image_height").real()
        finally:
            storage.release()
        if matrix is None or matrix.shape != (3, 3) or not width or not height:
            raise ValueError(
                f"camera file {str(path)!r} needs camera_matrix (3x3), image_width and image_height"
            )
        coeffs = () if dist is None else tuple(float(c) for c in dist.ravel())
        return Camera(float(matrix[0, 0]), float(matrix[1, 1]), float(matrix[0, 2]),
                      float(matrix[1, 2]), int(width), int(height), coeffs)


def project(camera: Camera, points: Tensor, min_depth: float = 1e-3) -> tuple[Tensor, Tensor]:
    """Pinhole projection of camera-frame points to pixels.

    Points at or behind ``min_depth`` are projected as if at ``min_depth`` (finite, with a
    gradient) and flagged in the returned mask, so a candidate that flies behind the camera
    does not poison a batch with infinities.

    Args:
        camera: intrinsics.
        points: (..., 3) camera-frame points, metres (e.g. (B, T, V, 3)).
        min_depth: smallest depth used in the division, metres.

    Returns:
        pixels: (..., 2) pixel coordinates (u right, v down).
        in_front: (...) bool, depth > min_depth.
    """
    depth = points[..., 2]
    in_front = depth > min_depth
    safe = depth.clamp(min=min_depth)
    u = camera.fx * points[..., 0] / safe + camera.cx
    v = camera.fy * points[..., 1] / safe + camera.cy
    return torch.stack((u, v), dim=-1), in_front


def gravity_direction(tilt: Tensor, roll: Tensor) -> Tensor:
    """Unit gravity direction in the camera frame.

    Args:
        tilt: (...) radians.
        roll: (...) radians.

    Returns:
        (..., 3) ``(sin(roll) cos(tilt), cos(roll) cos(tilt), sin(tilt))``.
    """
    cos_tilt = torch.cos(tilt)
    return torch.stack((torch.sin(roll) * cos_tilt, torch.cos(roll) * cos_tilt, torch.sin(tilt)), -1)


def tilt_roll_from_direction(direction: Tensor) -> tuple[Tensor, Tensor]:
    """Inverse of :func:`gravity_direction` for (..., 3) directions (normalised first).

    Returns:
        tilt, roll: (...) radians.
    """
    unit = direction / direction.norm(dim=-1, keepdim=True)
    tilt = torch.asin(unit[..., 2].clamp(-1.0, 1.0))
    roll = torch.atan2(unit[..., 0], unit[..., 1])
    return tilt, roll


def _axis_rotation(angle: float, axis: int) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    rot = np.eye(3)
    rot[i, i], rot[i, j], rot[j, i], rot[j, j] = c, -s, s, c
    return rot


def rectifying_rotation(tilt: float, roll: float) -> np.ndarray:
    """(3, 3) rotation of the camera frame that takes gravity to the image's +y axis.

    ``rectifying_rotation(t, r) @ gravity_direction(t, r) = (0, 1, 0)``: first undo the roll
    about the optical axis, then the tilt about the x axis.
    """
    return _axis_rotation(-tilt, 0) @ _axis_rotation(roll, 2)


def rectifying_homography(camera: Camera, tilt: float, roll: float) -> np.ndarray:
    """(3, 3) homography from image pixels to pixels of a virtual camera with the same
    intrinsics, rotated about its centre so that gravity points straight down the image
    (the paper's experiment 3). Use with ``cv2.warpPerspective``.
    """
    K = camera.K
    return K @ rectifying_rotation(tilt, roll) @ np.linalg.inv(K)
