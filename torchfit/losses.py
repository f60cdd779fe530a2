"""Silhouette targets and losses: observed masks resampled into each frame's crop window.

The paper's objective (eq. 5.1) is the sum over frames of the squared difference between the
simulated and the observed silhouette; here both live on the same per-frame crop grid so that the
cost follows the object's size, not the video's.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d
from torch import Tensor

__all__ = ["sample_targets", "silhouette_loss", "mask_moments", "central_moments", "raw_from_central"]


def sample_targets(masks: Tensor, windows: Tensor, size: tuple[int, int]) -> Tensor:
    """Observed masks seen through crop windows, area-averaged to the crop's pixel size.

    Args:
        masks: (T, H, W) float masks in [0, 1], image pixels.
        windows: (T, 3) windows ``(u0, v0, stride)`` (see :mod:`torchfit.render`).
        size: crop ``(h, w)``.

    Returns:
        (T, h, w) coverage of the observed object per crop pixel, zero outside the image.
    """
    height, width = masks.shape[-2:]
    crop_h, crop_w = size
    out = []
    for mask, (u0, v0, stride) in zip(masks, windows.tolist()):
        image = mask[None, None]
        if stride > 1.0:  # average over the crop pixel's footprint before sampling
            blur = 0.5 * stride
            kernel = 2 * int(2.5 * blur) + 1
            image = gaussian_blur2d(image, (kernel, kernel), (blur, blur), border_type="constant")
        cols = u0 + stride * torch.arange(crop_w, dtype=masks.dtype, device=masks.device)
        rows = v0 + stride * torch.arange(crop_h, dtype=masks.dtype, device=masks.device)
        grid = torch.stack(torch.meshgrid(2 * cols / (width - 1) - 1, 2 * rows / (height - 1) - 1,
                                          indexing="xy"), -1)
        out.append(F.grid_sample(image, grid[None], mode="bilinear", padding_mode="zeros",
                                 align_corners=True)[0, 0])
    return torch.stack(out)


def _centroid(image: Tensor) -> Tensor:
    """(..., h, w) coverage -> (..., 2) centroid (x, y) in crop units (0 to 1 across the crop)."""
    height, width = image.shape[-2:]
    rows = torch.linspace(0, 1, height, dtype=image.dtype, device=image.device)
    cols = torch.linspace(0, 1, width, dtype=image.dtype, device=image.device)
    mass = image.sum(dim=(-2, -1)).clamp(min=1e-6)
    return torch.stack(((image.sum(-2) * cols).sum(-1), (image.sum(-1) * rows).sum(-1)), -1) / mass[..., None]


def silhouette_loss(coverage: Tensor, target: Tensor, weights: Tensor, centroid_weight: float = 1.0) -> Tensor:
    """Mean squared silhouette difference per candidate (the paper's SSD, per crop pixel), plus a
    centroid term: the squared distance between the rendered and the observed coverage
    centroids in units of the crop size, which keeps a pull on translation when the two
    silhouettes barely overlap.

    Args:
        coverage: (B, T, h, w) rendered coverage.
        target: (T, h, w) observed coverage on the same grids.
        weights: (T,) frame weights (0 for frames left out).
        centroid_weight: weight of the centroid term.

    Returns:
        (B,) loss.
    """
    per_frame = (coverage - target).square().mean(dim=(-2, -1))  # (B, T)
    if centroid_weight:
        offset = _centroid(coverage) - _centroid(target)  # (B, T, 2), crop sizes
        per_frame = per_frame + centroid_weight * offset.square().sum(-1)
    return (per_frame * weights).sum(-1) / weights.sum().clamp(min=1e-12)


def coverage_residuals(coverage: Tensor, target: Tensor, weights: Tensor, centroid_weight: float = 1.0) -> Tensor:
    """The terms of :func:`silhouette_loss` as residuals: their squared sum is the loss.

    Args: as :func:`silhouette_loss` (``coverage`` (B, T, h, w), ``target`` (T, h, w), ``weights`` (T,)).

    Returns:
        (B, T, h w + 2): per frame the coverage differences scaled by ``sqrt(w_t / (h w Σw))``,
        then the centroid offset (crop units) scaled by ``sqrt(centroid_weight w_t / Σw)``.
    """
    height, width = coverage.shape[-2:]
    share = weights / weights.sum().clamp(min=1e-12)  # (T,)
    pixels = (coverage - target) * (share / (height * width)).sqrt()[:, None, None]
    offset = (_centroid(coverage) - _centroid(target)) * (centroid_weight * share).sqrt()[:, None]  # (B, T, 2)
    return torch.cat((pixels.flatten(-2), offset), -1)


def central_moments(raw: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Area (N,), centroid (N, 2) and covariance (N, 2, 2), as :func:`mask_moments` gives them,
    from (N, 6) raw moments ``(m00, m10, m01, m20, m11, m02)`` about one origin (the centroid is
    about that origin too; 0 where the area is)."""
    area = raw[:, 0]
    safe = area.clamp(min=1e-12)
    cu, cv = raw[:, 1] / safe, raw[:, 2] / safe
    cuu, cuv, cvv = raw[:, 3] / safe - cu * cu, raw[:, 4] / safe - cu * cv, raw[:, 5] / safe - cv * cv
    cov = torch.stack((torch.stack((cuu, cuv), -1), torch.stack((cuv, cvv), -1)), -2)
    return area, torch.stack((cu, cv), -1), cov


def raw_from_central(area: Tensor, centroid: Tensor, cov: Tensor) -> Tensor:
    """(N, 6) raw moments ``(m00, m10, m01, m20, m11, m02)`` about the origin of the centroid
    from area (N,), centroid (N, 2) and covariance (N, 2, 2): the inverse of :func:`central_moments`."""
    cu, cv = centroid[..., 0], centroid[..., 1]
    return torch.stack((area, area * cu, area * cv, area * (cov[..., 0, 0] + cu * cu),
                        area * (cov[..., 0, 1] + cu * cv), area * (cov[..., 1, 1] + cv * cv)), -1)


def mask_moments(masks: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Area, centroid and second central moments of (T, H, W) masks.

    Returns:
        area: (T,) pixels.
        centroid: (T, 2) ``(u, v)`` pixels.
        covariance: (T, 2, 2) pixels².
    """
    height, width = masks.shape[-2:]
    u = torch.arange(width, dtype=masks.dtype, device=masks.device)
    v = torch.arange(height, dtype=masks.dtype, device=masks.device)
    flat = masks.reshape(-1, height, width)
    # sums over each row first (matrix products), then over the rows: no (T, H, W) temporaries
    rows = flat @ torch.stack((torch.ones_like(u), u), -1)  # (T, H, 2): sum m, sum m u per row
    area = rows[..., 0].sum(-1)
    safe = area.clamp(min=1e-12)
    cu = rows[..., 1].sum(-1) / safe
    cv = rows[..., 0] @ v / safe
    du = u - cu[:, None]  # (T, W)
    dv = v - cv[:, None]  # (T, H)
    central = torch.bmm(flat, torch.stack((du, du * du), -1))  # (T, H, 2): sum m du, sum m du² per row
    cov_uu = central[..., 1].sum(-1)
    cov_uv = (central[..., 0] * dv).sum(-1)
    cov_vv = (rows[..., 0] * dv * dv).sum(-1)
    cov = torch.stack([torch.stack([cov_uu, cov_uv], -1), torch.stack([cov_uv, cov_vv], -1)], -2) / safe[:, None, None]
    shape = masks.shape[:-2]
    area, cu, cv, cov = area.reshape(shape), cu.reshape(shape), cv.reshape(shape), cov.reshape(*shape, 2, 2)
    return area, torch.stack((cu, cv), -1), cov
