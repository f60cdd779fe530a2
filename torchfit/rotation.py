"""Quaternion and rotation helpers shared by dynamics, rendering and metrics.

Quaternions are ``(w, x, y, z)``, real part first, as kornia and PyTorch3D; conversions to and
from matrices are kornia's.
"""

from __future__ import annotations

import torch
from kornia.geometry.conversions import (
    axis_angle_to_quaternion,
    quaternion_to_rotation_matrix,
    rotation_matrix_to_quaternion,
)
from torch import Tensor

__all__ = [
    "quat_multiply",
    "quat_to_matrix",
    "matrix_to_quat",
    "axis_angle_to_quat",
    "rotation_angle",
    "check_unit_quaternion",
]


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a ⊗ b``.

    Args:
        a: (..., 4) quaternions (w, x, y, z).
        b: (..., 4) quaternions, broadcastable with ``a``.

    Returns:
        (..., 4) the product; ``R(a ⊗ b) = R(a) @ R(b)``.
    """
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def quat_to_matrix(quat: Tensor) -> Tensor:
    """Rotation matrices of (not necessarily unit) quaternions; normalises first.

    Args:
        quat: (..., 4) quaternions (w, x, y, z).

    Returns:
        (..., 3, 3) rotation matrices.
    """
    return quaternion_to_rotation_matrix(quat)


def matrix_to_quat(rot: Tensor) -> Tensor:
    """Unit quaternions of rotation matrices, sign chosen with ``w >= 0``.

    Args:
        rot: (..., 3, 3) rotation matrices.

    Returns:
        (..., 4) unit quaternions (w, x, y, z).
    """
    quat = rotation_matrix_to_quaternion(rot.contiguous())
    return torch.where(quat[..., :1] < 0, -quat, quat)


def axis_angle_to_quat(axis_angle: Tensor) -> Tensor:
    """Quaternions of rotation vectors (axis times angle in radians).

    Args:
        axis_angle: (..., 3) rotation vectors.

    Returns:
        (..., 4) unit quaternions (w, x, y, z).
    """
    return axis_angle_to_quaternion(axis_angle)


def rotation_angle(rot_a: Tensor, rot_b: Tensor) -> Tensor:
    """Geodesic angle between rotations, radians.

    Args:
        rot_a: (..., 3, 3) rotation matrices.
        rot_b: (..., 3, 3) rotation matrices, broadcastable with ``rot_a``.

    Returns:
        (...) the angle of ``rot_a^T rot_b`` in [0, pi].
    """
    trace = (rot_a * rot_b).sum(dim=(-2, -1))
    return torch.acos(((trace - 1.0) / 2.0).clamp(-1.0, 1.0))


def check_unit_quaternion(quat: Tensor, name: str = "quaternion", atol: float = 1e-3) -> None:
    """Raise ``ValueError`` unless every quaternion of ``quat`` (..., 4) has unit norm."""
    if quat.shape[-1] != 4:
        raise ValueError(f"{name} must have shape (..., 4) (w, x, y, z), got {tuple(quat.shape)}")
    norms = quat.detach().norm(dim=-1)
    bad = (norms - 1.0).abs() > atol
    if bool(bad.any()):
        worst = float(norms[bad].flatten()[0])
        raise ValueError(
            f"{name} must be unit quaternions (w, x, y, z); found norm {worst:.6g} "
            f"({int(bad.sum())} of {norms.numel()} not unit)"
        )
