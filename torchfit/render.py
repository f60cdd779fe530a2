"""Sigmoid-edge soft silhouettes of a posed shape, inside a crop window per frame.

Why convex parts and contour edges rather than triangles: the silhouette of a convex body is a
convex polygon bounded by the projections of its *contour edges* (edges between a face that
faces the camera and one that does not), and a convex polygon's signed distance inside is the
largest signed distance to its edge lines. So each convex part's coverage is

    c_p = sigmoid(-d_p / sigma),   d_p(u) = max_k (n_k · u - o_k)   (over its contour edges k),

and the shape's coverage is the soft union ``1 - prod_p (1 - c_p)``. Compared with a soft union
over triangles (Soft Rasterizer) this has no half-covered seams along interior triangle edges,
and a box costs 4-6 edge lines per pixel instead of 12 triangles. A non-convex mesh is split into
convex parts (see :mod:`torchfit.shape`); a flat triangle is a part whose three edges are always
contour edges, so the triangle soft rasteriser is the special case.

Pixel grid: crop pixel ``(row, col)`` has its centre at image pixel
``(u0 + col * stride, v0 + row * stride)`` for the window ``(u0, v0, stride)``; ``sigma`` is in
crop pixels. The pixel loop is a custom autograd function that recomputes what it needs in the
backward pass, chunk by chunk, so memory stays at the size of the output.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from .camera import Camera, project
from .losses import central_moments

__all__ = [
    "RenderMesh",
    "Shutter",
    "contour_lines",
    "coverage_from_lines",
    "coverage_jvp",
    "crop_windows",
    "full_window",
    "render_silhouettes",
    "set_compile",
    "silhouette_moments",
    "silhouette_lines",
    "window_lines",
]

_FAR = 1.0e4  # a masked edge line's offset, crop pixels: never the maximum
SPHERE_EDGES = 32  # a sphere's outline as a polygon of this many sides (:func:`_sphere_ends`)


@dataclass(frozen=True)
class RenderMesh:
    """A shape's convex parts as padded tensors.

    Attributes:
        vertices: (V, 3) all parts' vertices, mesh coordinates, metres.
        edges: (P, E, 2) int64 indices into ``vertices`` (padded edges are masked).
        normals: (P, E, 2, 3) outward normals of each edge's two faces, mesh axes.
        offsets: (P, E, 2) plane offsets ``n · x`` of those faces, metres.
        valid: (P, E) bool, False on padding.
        centroids: (P, 3) a point inside each part, mesh coordinates.
        edge_facets: (P, E, 2) int64 the facet of each edge's two faces, indices into
            ``facet_weights`` (0 on padding).
        facet_weights: (F, V) each facet's boundary vertices, each one over their count
            (:attr:`torchfit.shape.ConvexPart.facet_weights`, all parts').
        sphere: (4,) a round shape's (:attr:`torchfit.shape.Shape.round`) centre (mesh
            coordinates) and radius, metres, or None. Where it is set the silhouette is the
            sphere's own outline (:func:`_sphere_ends`), not the mesh's: a tessellated ball's
            outline changes as it turns, so its hidden orientation and spin moved the fits.
    """

    vertices: Tensor
    edges: Tensor
    normals: Tensor
    offsets: Tensor
    valid: Tensor
    centroids: Tensor
    edge_facets: Tensor
    facet_weights: Tensor
    sphere: Tensor | None = None

    @staticmethod
    def from_shape(shape, dtype: torch.dtype = torch.float32, device="cpu") -> "RenderMesh":
        parts = shape.parts
        n_edges = max(len(p.edges) for p in parts)
        vertices, edges, normals, offsets, valid, facets = [], [], [], [], [], []
        base = facet_base = 0
        weights = np.zeros((sum(len(p.facet_weights) for p in parts), sum(len(p.vertices) for p in parts)))
        for part in parts:
            pad = n_edges - len(part.edges)
            edges.append(np.concatenate([part.edges + base, np.zeros((pad, 2), np.int64)]))
            normals.append(np.concatenate([part.edge_normals, np.zeros((pad, 2, 3))]))
            offsets.append(np.concatenate([part.edge_offsets, np.zeros((pad, 2))]))
            valid.append(np.arange(n_edges) < len(part.edges))
            facets.append(np.concatenate([part.edge_facets + facet_base, np.zeros((pad, 2), np.int64)]))
            weights[facet_base:facet_base + len(part.facet_weights), base:base + len(part.vertices)] = part.facet_weights
            vertices.append(part.vertices)
            base += len(part.vertices)
            facet_base += len(part.facet_weights)

        def as_tensor(value, kind=dtype):
            return torch.as_tensor(np.stack(value) if isinstance(value, list) else value,
                                   dtype=kind, device=device)

        return RenderMesh(
            as_tensor(np.concatenate(vertices)),
            as_tensor(edges, torch.int64),
            as_tensor(normals),
            as_tensor(offsets),
            as_tensor(valid, torch.bool),
            as_tensor(np.stack([p.centroid for p in parts])),
            as_tensor(facets, torch.int64),
            as_tensor(weights),
            as_tensor(_sphere_of(shape)) if shape.round else None,
        )


def _sphere_of(shape) -> np.ndarray:
    """(4,) a round shape's centre and radius: the centre of its mesh's volume (uniform density,
    whatever mass the user gave) and the median distance of its mesh's vertices from it (a
    tessellation's vertices lie on the sphere; the render parts' may be a reduced hull, scaled)."""
    centre = np.asarray(shape.mesh.center_mass, dtype=np.float64)
    return np.append(centre, np.median(np.linalg.norm(np.asarray(shape.mesh.vertices) - centre, axis=1)))


@dataclass(frozen=True)
class Shutter:
    """A rolling shutter: each image row is exposed at its own time, first order in the delay.

    A point at ``x`` (camera frame) is drawn where the body's motion takes it by the time its
    row is exposed: ``x + Δ(y) (v + ω × (x - t))``, with ``v`` the mesh origin's velocity, ``t``
    its position and ``ω`` the angular velocity at the frame's stated time, and ``y`` the row of
    the moved point (a fixed point: the row moves with the point, by ``δ ẏ`` of the delay, ~3 %
    for a point crossing 1000 px/s at 30 µs/row; one step from the frame-time row leaves
    ``(δ ẏ)²``). The error of the first order, ``½ a Δ²`` and ``½ (ω Δ)² r``, is ~0.3 mm for a
    7 ms delay (30 µs/row, 240 rows off centre), ω 10 rad/s and a 10 cm body. Which edges are
    contour edges is decided face by face, each at its facet's time (the mean of its boundary
    vertices' row delays), the same for every edge that borders it, so each part's contour edges
    close into a loop: decided at each edge's own time, a face turning during the readout could
    count as facing at one of its edges and not at another, and the open contour's exact moments
    were those of no outline (1-10 % of the poses of a thrown box, cylinder or ball at 3 m/s,
    10 rad/s and 30 µs/row; 2026-11-29). Decided at the frame's time instead, a face seen
    nearly edge-on could be counted on the wrong side and the silhouette lost most of its area
    (a box of the rolling-shutter set, -65 % in one frame).

    Attributes:
        delay: (N, V) pinhole pixel rows -> (N, V) seconds after the frame's stated time
            (e.g. :meth:`torchfit.effects.RollingShutter.row_delay`), rows in the order of the
            N poses.
        velocity: (N, 3) the mesh origin's velocity, camera frame, m/s.
        angular_velocity: (N, 3) camera frame, rad/s.
    """

    delay: Callable[[Tensor], Tensor]
    velocity: Tensor
    angular_velocity: Tensor

    def move(self, camera: Camera, points: Tensor, trans: Tensor, steps: int = 1) -> tuple[Tensor, Tensor]:
        """(N, V, 3) camera-frame points of N poses with origins ``trans`` (N, 3) -> (N, V, 3)
        where each is at its row's time, and those (N, V) times (seconds after the frame's): the
        row where the point is then, found by ``steps`` fixed-point steps from its row at the
        frame's time."""
        spin = self.angular_velocity.unsqueeze(1).expand_as(points)
        speed = self.velocity.unsqueeze(1) + torch.cross(spin, points - trans.unsqueeze(1), dim=-1)
        moved = points
        for _ in range(steps + 1):
            delay = self.delay(project(camera, moved)[0][..., 1])
            moved = points + delay.unsqueeze(-1) * speed
        return moved, delay

    def drift(self, rot: Tensor, trans: Tensor) -> Tensor:
        """(N, 3) the rate of change of ``Rᵀ t`` (the camera's position in mesh coordinates,
        negated) per second: ``Rᵀ (v - ω × t)`` for (N, 3, 3) rotations and (N, 3) origins."""
        along = self.velocity - torch.cross(self.angular_velocity, trans, dim=-1)
        return torch.einsum("nji,nj->ni", rot, along)


class _Contour(NamedTuple):
    lines: Tensor  # (N, P, K, 3), see contour_lines
    edges: Tensor  # (N, P, K, 2, 2) each contour edge's ends (u, v), walked so that its part's
    # outward normal (a, b) is (dv, -du) / |d|: anticlockwise in (u, v) taken as x and y
    drawn: Tensor  # (N, P, K) bool: a contour edge of a shape in front of the camera


def contour_lines(mesh: RenderMesh, camera: Camera, rot: Tensor, trans: Tensor,
                  distort: Callable[[Tensor], Tensor] | None = None, shutter: Shutter | None = None) -> Tensor:
    """Edge lines of each convex part's silhouette, in image pixels.

    Args:
        mesh: the shape's convex parts.
        camera: intrinsics.
        rot: (N, 3, 3) rotations ``R`` (mesh to camera).
        trans: (N, 3) translations ``t``, metres.
        distort: optional lens model on normalised image coordinates, (N, V, 2) -> (N, V, 2)
            (e.g. :meth:`torchfit.effects.LensDistortion.distort`). The vertices are distorted
            and the edges stay straight: exact at the vertices, and for an object a small
            fraction of the image wide the edges' curvature is far below a pixel.
        shutter: optional rolling shutter (:class:`Shutter`, N poses' motion): the vertices
            are moved to their rows' times before projection (and distortion).

    Returns:
        (N, P, K, 3) lines ``(a, b, c)``: ``a u + b v + c`` is the signed distance in pixels
        from pixel ``(u, v)`` to the edge's line, negative on the part's side. Slots beyond a
        part's contour edges hold a far-away line that is never the maximum. A part with a
        vertex behind the camera is not drawn.
    """
    return _contour(mesh, camera, rot, trans, distort, shutter).lines


class _Posed(NamedTuple):
    """What a batch of poses' contours need (:func:`_posed`): :func:`_contour_edges` finds the
    contour edges from it, :func:`_end_pixels` projects their ends; rows can be taken in slices
    (:meth:`rows`). No vertex is projected here."""

    rot: Tensor  # (N, 3, 3) mesh to camera
    trans: Tensor  # (N, 3) metres
    behind: Tensor  # (N,) a vertex at or behind the camera's nearest depth: the shape is not drawn
    centre_px: Tensor  # (N, P, 2) each part's centroid's pixel (distorted where there is a lens)
    trans_body: Tensor  # (N, 3) the camera's position in mesh coordinates, negated: R^T t
    moved: Tensor | None  # (N, V, 3) a rolling shutter's vertices at their rows' times, camera frame
    facet_delay: Tensor | None  # (N, F) a rolling shutter's row delay of each facet (its boundary's mean)
    drift: Tensor | None  # (N, 3) the shutter's motion of the camera in mesh coordinates per unit delay

    def rows(self, start: int, stop: int) -> "_Posed":
        return _Posed(*(None if x is None else x[start:stop] for x in self))


def _contour(mesh: RenderMesh, camera: Camera, rot: Tensor, trans: Tensor,
             distort: Callable[[Tensor], Tensor] | None, shutter: Shutter | None) -> _Contour:
    """Each convex part's contour edges as lines (:func:`contour_lines`) and as walked segments."""
    posed, ends, keep, _ = _contour_ends(mesh, camera, rot, trans, distort, shutter)
    return _lines_of(ends, keep, posed)


def _contour_ends(mesh: RenderMesh, camera: Camera, rot: Tensor, trans: Tensor,
                  distort: Callable[[Tensor], Tensor] | None, shutter: Shutter | None,
                  budget: int = 1 << 20) -> tuple[_Posed, Tensor, Tensor, int]:
    """The poses (:func:`_posed`), the (N, P, K, 2, 2) pixels of each part's contour edges' ends,
    the (N, P, K) flags of the slots that hold one, and the poses per chunk of ``budget``
    elements of the facing test.

    The faces' facing test picks the contour edges, the poses in chunks; then only those edges'
    ends are projected and distorted (:func:`_end_pixels`), all poses at once: a lens's
    parameters are one per candidate, repeated over its rows.
    """
    if mesh.sphere is not None:
        posed, ends = _sphere_ends(mesh.sphere, camera, rot, trans, distort, shutter)
        keep = torch.ones(ends.shape[:3], dtype=torch.bool, device=ends.device)
        return posed, ends, keep, max(1, budget // (2 * SPHERE_EDGES))
    posed = _posed(mesh, camera, rot, trans, distort, shutter)
    step = max(1, budget // max(mesh.normals.shape[0] * mesh.normals.shape[1] * 2, 1))
    chunks = [_contour_edges(mesh, posed.rows(i, i + step)) for i in range(0, len(rot), step)]
    if len(chunks) == 1:
        edge_idx, keep = chunks[0]
    else:  # each chunk as many slots as its own most; padded slots are not contour edges
        width = max(idx.shape[2] for idx, _ in chunks)
        edge_idx = torch.cat([torch.nn.functional.pad(idx, (0, 0, 0, width - idx.shape[2])) for idx, _ in chunks])
        keep = torch.cat([torch.nn.functional.pad(k, (0, width - k.shape[2])) for _, k in chunks])
    return posed, _end_pixels(mesh, camera, posed, edge_idx, distort), keep, step


def _posed(mesh: RenderMesh, camera: Camera, rot: Tensor, trans: Tensor,
           distort: Callable[[Tensor], Tensor] | None, shutter: Shutter | None,
           min_depth: float = 1e-3) -> _Posed:
    """What the edges' facing test and the projection of their ends need, for N poses
    (:func:`contour_lines`' arguments). A rolling shutter moves every vertex to its row's time
    (its rows are the projected vertices'); otherwise nothing is computed per vertex but, for the
    poses whose mesh could reach ``min_depth``, the vertices' depths (a vertex there hides the
    shape, as :func:`torchfit.camera.project`'s ``in_front``)."""
    centres = torch.einsum("nij,pj->npi", rot, mesh.centroids) + trans.unsqueeze(1)
    moved = facet_delay = drift = None
    if shutter is not None:
        points = torch.einsum("nij,vj->nvi", rot, mesh.vertices) + trans.unsqueeze(1)  # (N, V, 3)
        moved, vertex_delay = shutter.move(camera, points, trans)
        facet_delay = vertex_delay @ mesh.facet_weights.T  # (N, F)
        centres = shutter.move(camera, centres, trans)[0]
        drift = shutter.drift(rot, trans)
        behind = ~(moved[..., 2] > min_depth).all(dim=1)  # as project's in_front
    else:  # every vertex's depth only where the mesh's reach from its origin could cross min_depth
        reach = float(mesh.vertices.detach().norm(dim=-1).max())
        behind = torch.zeros(len(rot), dtype=torch.bool, device=rot.device)
        near = trans[:, 2].detach() - reach <= min_depth
        if bool(near.any()):
            depth = torch.einsum("nj,vj->nv", rot[near, 2], mesh.vertices) + trans[near, 2:]
            behind[near] = ~(depth > min_depth).all(dim=1)
    centre_px, _ = project(camera, centres)  # (N, P, 2)
    if distort is not None:
        centre_px = _distort_pixels(camera, distort, centre_px)
    trans_body = torch.einsum("nji,nj->ni", rot, trans)  # (N, 3)
    return _Posed(rot, trans, behind, centre_px, trans_body, moved, facet_delay, drift)


def _sphere_ends(sphere: Tensor, camera: Camera, rot: Tensor, trans: Tensor,
                 distort: Callable[[Tensor], Tensor] | None, shutter: Shutter | None,
                 min_depth: float = 1e-3, count: int = SPHERE_EDGES) -> tuple[_Posed, Tensor]:
    """A sphere's outline for N poses: the poses (:class:`_Posed`, one part) and the (N, 1, K, 2,
    2) pixels of the ends of its K = ``count`` sides.

    The rays from the camera that touch a sphere of centre ``c`` and radius ``r`` form a cone;
    on the normalised image plane ``p = (x, y, 1)`` it is the ellipse ``(p · c)² = h |p|²``,
    ``h = |c|² - r²``: centre ``x₀ = c_xy c_z / (c_z² - r²)``, ``(x - x₀)ᵀ S⁻¹ (x - x₀) = 1``.
    Its outline is drawn as the affine image ``x₀ + L u`` (``L Lᵀ = S``) of a regular K-gon
    ``u`` whose area is the unit circle's (circumradius ``√(2π / (K sin(2π/K)))``), so the
    polygon's area and centroid are the ellipse's exactly and its second moments the ellipse's
    times one factor (1 + 2e-5 at 32 sides), whatever the pose. No rotation moves it. Each
    point is lifted to where its ray touches the sphere (the plane ``x · c = h``), so a lens
    distorts it and a rolling shutter moves it, with the centre's velocity (a turn carries the
    sphere's surface along itself), to its row's time (:meth:`Shutter.move`). A sphere within
    ``min_depth`` of the camera's plane is not drawn.
    """
    centre = torch.einsum("nij,j->ni", rot, sphere[:3]) + trans  # (N, 3)
    radius = sphere[3]
    behind = centre[:, 2] - radius <= min_depth  # its nearest point at min_depth or nearer
    # a sphere not drawn gets a harmless stand-in, so nothing below divides by zero or takes a
    # root of a negative number (which would poison the batch's gradients)
    stand_in = torch.zeros_like(centre)
    stand_in[:, 2] = 2 * radius.detach() + 1.0
    centre = torch.where(behind.unsqueeze(-1), stand_in, centre)
    across, depth = centre[:, :2], centre[:, 2]
    h = (centre * centre).sum(-1) - radius**2  # (N,)
    g = depth**2 - radius**2
    x0 = across * (depth / g).unsqueeze(-1)  # (N, 2) the ellipse's centre
    eye = torch.eye(2, dtype=centre.dtype, device=centre.device)
    outer = across.unsqueeze(-1) * across.unsqueeze(-2)  # (N, 2, 2)
    q = outer - h[:, None, None] * eye  # the conic's quadratic part, negative definite
    q_inv = -(eye + outer / g[:, None, None]) / h[:, None, None]  # Sherman-Morrison
    k = torch.einsum("ni,nij,nj->n", x0, q, x0) - (depth**2 - h)
    spread = k[:, None, None] * q_inv  # (N, 2, 2) S, positive definite
    a = spread[:, 0, 0].sqrt()
    b = spread[:, 1, 0] / a
    c = (spread[:, 1, 1] - b * b).clamp(min=0.0).sqrt()
    angle = torch.arange(count + 1, dtype=centre.dtype, device=centre.device) * (2 * math.pi / count)
    scale = math.sqrt(2 * math.pi / (count * math.sin(2 * math.pi / count)))
    u, v = scale * angle.cos(), scale * angle.sin()  # (K + 1,), the first point repeated
    image = torch.stack((x0[:, :1] + a[:, None] * u, x0[:, 1:] + b[:, None] * u + c[:, None] * v), -1)
    rays = torch.cat((image, torch.ones_like(image[..., :1])), -1)  # (N, K + 1, 3)
    points = rays * (h.unsqueeze(-1) / torch.einsum("nkj,nj->nk", rays, centre)).unsqueeze(-1)
    centres = centre.unsqueeze(1)  # (N, 1, 3)
    if shutter is not None:
        velocity = shutter.velocity + torch.cross(shutter.angular_velocity, centre - trans, dim=-1)
        moving = Shutter(shutter.delay, velocity, torch.zeros_like(velocity))
        points = moving.move(camera, points, trans)[0]
        centres = moving.move(camera, centres, trans)[0]
    pixels, _ = project(camera, points)
    centre_px, _ = project(camera, centres)
    if distort is not None:
        pixels = _distort_pixels(camera, distort, pixels)
        centre_px = _distort_pixels(camera, distort, centre_px)
    ends = torch.stack((pixels[:, :-1], pixels[:, 1:]), dim=-2).unsqueeze(1)  # (N, 1, K, 2, 2)
    trans_body = torch.einsum("nji,nj->ni", rot, trans)
    return _Posed(rot, trans, behind, centre_px, trans_body, None, None, None), ends


def _contour_edges(mesh: RenderMesh, posed: _Posed) -> tuple[Tensor, Tensor]:
    """(n, P, K, 2) the vertex indices of each part's contour edges, K the most of any part and
    pose, and (n, P, K) which slots hold one: an edge between a face that faces the camera and
    one that does not."""
    # a face faces the camera (at the origin) when n_w · x_w < 0; in mesh coordinates that is
    # o + n · (Rᵀ t) < 0
    side = mesh.offsets + torch.einsum("pefk,nk->npef", mesh.normals, posed.trans_body)
    if posed.facet_delay is not None:  # each face at the time its facet's rows are exposed (their mean)
        drift = torch.einsum("pefk,nk->npef", mesh.normals, posed.drift)
        side = side + posed.facet_delay[:, mesh.edge_facets] * drift
    facing = side < 0
    contour = (facing[..., 0] != facing[..., 1]) & mesh.valid  # (n, P, E)
    count = int(contour.sum(-1).max()) if contour.numel() else 0
    count = max(count, 1)
    order = torch.argsort(contour.to(torch.int8), dim=-1, descending=True, stable=True)[..., :count]
    keep = torch.gather(contour, -1, order)  # (n, P, K)
    edge_idx = torch.gather(mesh.edges.expand(contour.shape[0], -1, -1, -1), 2,
                            order.unsqueeze(-1).expand(-1, -1, -1, 2))  # (n, P, K, 2)
    return edge_idx, keep


def _end_pixels(mesh: RenderMesh, camera: Camera, posed: _Posed, edge_idx: Tensor,
                distort: Callable[[Tensor], Tensor] | None) -> Tensor:
    """(N, P, K, 2 ends, 2 uv) image pixels of the (N, P, K, 2) vertices ``edge_idx``: moved by
    the rolling shutter where there is one, projected, then distorted by the lens. Whichever is
    fewer is projected: the contour edges' ends (a ball's icosphere drawn as a mesh, 256 hull
    vertices and some 70 ends), or every vertex, then gathered (a box's 8 vertices and up to 12
    ends)."""
    ends = edge_idx.reshape(len(edge_idx), -1)  # (N, M)
    if ends.shape[1] < len(mesh.vertices):
        if posed.moved is not None:
            points = torch.gather(posed.moved, 1, ends.unsqueeze(-1).expand(-1, -1, 3))  # (N, M, 3)
        else:
            points = torch.einsum("nij,nmj->nmi", posed.rot, mesh.vertices[ends]) + posed.trans.unsqueeze(1)
        index = None
    else:
        points = (posed.moved if posed.moved is not None
                  else torch.einsum("nij,vj->nvi", posed.rot, mesh.vertices) + posed.trans.unsqueeze(1))
        index = ends
    pixels, _ = project(camera, points)
    if distort is not None:
        pixels = _distort_pixels(camera, distort, pixels)
    if index is not None:
        pixels = torch.gather(pixels, 1, index.unsqueeze(-1).expand(-1, -1, 2))
    return pixels.reshape(*edge_idx.shape, 2)


def _lines_of(ends: Tensor, keep: Tensor, posed: _Posed) -> _Contour:
    """The :class:`_Contour` of contour edges with (N, P, K, 2, 2) ``ends`` (pixels) and (N, P, K)
    ``keep`` flags: each edge's line, facing away from its part's centre."""
    centre_px = posed.centre_px
    start, direction = ends[..., 0, :], ends[..., 1, :] - ends[..., 0, :]
    length = direction.norm(dim=-1).clamp(min=1e-9)
    a = direction[..., 1] / length
    b = -direction[..., 0] / length
    c = -(a * start[..., 0] + b * start[..., 1])
    side = a * centre_px[..., None, 0] + b * centre_px[..., None, 1] + c  # centre must be < 0
    sign = torch.where(side > 0, -1.0, 1.0).to(a.dtype)
    lines = torch.stack((a * sign, b * sign, c * sign), dim=-1)  # (N, P, K, 3)
    behind = posed.behind[:, None]  # (N, 1): any vertex behind hides the shape
    far = torch.tensor([0.0, 0.0, -_FAR], dtype=lines.dtype, device=lines.device)
    lines = torch.where(keep.unsqueeze(-1), lines, far)
    hide = torch.tensor([0.0, 0.0, _FAR], dtype=lines.dtype, device=lines.device)
    first = torch.zeros_like(keep)
    first[..., 0] = True
    lines = torch.where((behind.unsqueeze(-1) & first).unsqueeze(-1), hide, lines)
    # each edge walked so that (a, b) = (dv, -du) / |d|: the shoelace sum of a part is its area
    flip = (sign < 0).unsqueeze(-1)
    walked = torch.stack((torch.where(flip, ends[..., 1, :], ends[..., 0, :]),
                          torch.where(flip, ends[..., 0, :], ends[..., 1, :])), dim=-2)  # (N, P, K, 2, 2)
    return _Contour(lines, walked, keep & ~behind.unsqueeze(-1))


def _distort_pixels(camera: Camera, distort: Callable[[Tensor], Tensor], pixels: Tensor) -> Tensor:
    """(N, V, 2) pinhole pixels -> (N, V, 2) pixels through ``distort`` on normalised coordinates."""
    focal = pixels.new_tensor([camera.fx, camera.fy])
    centre = pixels.new_tensor([camera.cx, camera.cy])
    return distort((pixels - centre) / focal) * focal + centre


def window_lines(lines: Tensor, windows: Tensor) -> Tensor:
    """Re-express image-pixel lines in a crop's pixel units.

    Args:
        lines: (N, P, K, 3) lines in image pixels.
        windows: (N, 3) windows ``(u0, v0, stride)``.

    Returns:
        (N, P, K, 3) lines whose value at crop pixel ``(col, row)`` is the signed distance in
        crop pixels.
    """
    u0, v0, stride = (w[:, None, None] for w in windows.unbind(-1))
    a, b, c = lines.unbind(-1)
    return torch.stack((a, b, (a * u0 + b * v0 + c) / stride), dim=-1)


# ---------------------------------------------------------------------------------------------
# the pixel loop


def _grid(height: int, width: int, like: Tensor) -> tuple[Tensor, Tensor]:
    rows = torch.arange(height, dtype=like.dtype, device=like.device).view(1, 1, height, 1)
    cols = torch.arange(width, dtype=like.dtype, device=like.device).view(1, 1, 1, width)
    return rows, cols


def _basis(height: int, width: int, like: Tensor) -> Tensor:
    """(3, H*W) each crop pixel's ``(col, row, 1)``: a line's values on the grid are ``line @ basis``."""
    rows, cols = _grid(height, width, like)
    return torch.stack(torch.broadcast_tensors(cols, rows, torch.ones_like(cols)), 0).reshape(3, height * width)


def _distances(lines: Tensor, height: int, width: int, with_arg: bool = True) -> tuple[Tensor, Tensor | None]:
    """(N, P, H, W) signed distance to each part and (if asked) the index of the edge that attains it.

    All edges' values come from one matrix product and the maximum from one reduction (a loop
    over the edges took two ``where`` passes per edge); without the index the reduction is
    ``amax``, four times faster than ``max`` over that axis on the CPU.
    """
    count, parts = lines.shape[:2]
    values = lines @ _basis(height, width, lines)  # (N, P, K, H*W)
    if not with_arg:
        return values.amax(dim=2).view(count, parts, height, width), None
    dist, arg = values.max(dim=2)
    return dist.view(count, parts, height, width), arg.view(count, parts, height, width)


def _forward_chunk(lines: Tensor, height: int, width: int, inv_sigma: float) -> Tensor:
    dist, _ = _distances(lines, height, width, with_arg=False)
    return 1.0 - torch.sigmoid(dist * inv_sigma).prod(dim=1)


def _backward_chunk(lines: Tensor, grad: Tensor, height: int, width: int, inv_sigma: float) -> Tensor:
    dist, arg = _distances(lines, height, width)
    outside = torch.sigmoid(dist * inv_sigma)  # 1 - c_p, (N, P, H, W)
    # d(1 - prod_p s_p)/d dist_p = -(prod_q s_q) (1 - s_p) / sigma
    grad_dist = -(grad.unsqueeze(1) * outside.prod(dim=1, keepdim=True)) * (1 - outside) * inv_sigma
    # d dist / d (a, b, c) = (col, row, 1) for the edge attaining the maximum, 0 for the others
    return _at_edges(grad_dist, arg, lines.shape[2]) @ _basis(height, width, lines).T  # (N, P, K, 3)


def _at_edges(values: Tensor, arg: Tensor, edges: int) -> Tensor:
    """(N, P, K, H*W): ``values`` (N, P, H, W) placed at each pixel's attaining edge, 0 elsewhere."""
    count, parts = values.shape[:2]
    out = values.new_zeros(count, parts, edges, values.shape[2] * values.shape[3])
    return out.scatter_(2, arg.reshape(count, parts, 1, -1), values.reshape(count, parts, 1, -1))


_KERNELS = {"forward": _forward_chunk, "backward": _backward_chunk}


def set_compile(enabled: bool) -> bool:
    """Use ``torch.compile``d pixel loops (True) or eager ones (False).

    Returns whether compilation is active: it falls back to eager, with a log line, when the
    platform cannot compile.
    """
    if not enabled:
        _KERNELS.update(forward=_forward_chunk, backward=_backward_chunk)
        return False
    try:
        forward = torch.compile(_forward_chunk)
        backward = torch.compile(_backward_chunk)
        probe = torch.zeros(1, 1, 4, 3)
        forward(probe, 2, 2, 1.0)
        backward(probe, torch.ones(1, 2, 2), 2, 2, 1.0)
    except Exception as err:  # noqa: BLE001 - any compiler failure means eager
        import logging

        logging.getLogger(__name__).warning("torch.compile unavailable (%s); eager rendering", err)
        return set_compile(False)
    _KERNELS.update(forward=forward, backward=backward)
    return True


def _chunk_size(lines: Tensor, height: int, width: int, budget: int) -> int:
    per_item = lines.shape[1] * max(lines.shape[2], 4) * height * width
    return max(1, budget // max(per_item, 1))


class _Coverage(torch.autograd.Function):
    @staticmethod
    def forward(ctx, lines: Tensor, height: int, width: int, sigma: float, budget: int) -> Tensor:
        ctx.save_for_backward(lines)
        ctx.shape = (height, width, sigma, budget)
        step = _chunk_size(lines, height, width, budget)
        forward = _KERNELS["forward"]
        return torch.cat([forward(lines[i:i + step], height, width, 1.0 / sigma)
                          for i in range(0, lines.shape[0], step)]) if len(lines) else \
            lines.new_zeros(0, height, width)

    @staticmethod
    def backward(ctx, grad: Tensor):
        (lines,) = ctx.saved_tensors
        height, width, sigma, budget = ctx.shape
        step = _chunk_size(lines, height, width, budget)
        backward = _KERNELS["backward"]
        grad = grad.contiguous()
        grads = [backward(lines[i:i + step], grad[i:i + step], height, width, 1.0 / sigma)
                 for i in range(0, lines.shape[0], step)]
        return torch.cat(grads), None, None, None, None


def coverage_from_lines(lines: Tensor, height: int, width: int, *, sigma: float | None,
                        budget: int = 1 << 21) -> Tensor:
    """Soft (or hard) union of convex parts given by their edge lines, in crop pixels.

    Args:
        lines: (N, P, K, 3) lines from :func:`window_lines`.
        height, width: crop size, pixels.
        sigma: edge width in crop pixels; ``None`` gives the hard (binary) silhouette.
        budget: elements of the per-chunk (n, P, K, H, W) work set; bounds memory.

    Returns:
        (N, H, W) coverage in [0, 1].
    """
    if sigma is None:
        out = []
        step = _chunk_size(lines, height, width, budget)
        for i in range(0, lines.shape[0], step):
            dist, _ = _distances(lines[i:i + step].detach(), height, width, with_arg=False)
            out.append((dist < 0).any(dim=1).to(lines.dtype))
        return torch.cat(out) if out else lines.new_zeros(0, height, width)
    return _Coverage.apply(lines, height, width, float(sigma), budget)


def coverage_jvp(lines: Tensor, tangents: Tensor, height: int, width: int, *, sigma: float,
                 budget: int = 1 << 21) -> tuple[Tensor, Tensor]:
    """Soft coverage and its derivatives along many directions at once (forward mode).

    ``coverage_from_lines`` differentiated by hand: with ``s_p = sigmoid(d_p / sigma)`` and
    ``d_p = max_k (a_k col + b_k row + c_k)``, the derivative of ``1 - prod_p s_p`` along a
    tangent of the lines is ``-sum_p (prod_q s_q) (1 - s_p) / sigma * (t_a col + t_b row + t_c)``
    at the edge ``k`` that attains the maximum. Gauss-Newton needs the whole Jacobian; reverse
    mode would need one backward pass per pixel, this needs one pass for all ``M`` directions.

    Args:
        lines: (N, P, K, 3) lines from :func:`window_lines`.
        tangents: (N, M, P, K, 3) derivatives of the lines along ``M`` directions.
        height, width: crop size, pixels.
        sigma: edge width in crop pixels.
        budget: elements of the per-chunk (n, P, K, 3, H, W) work set; bounds memory.

    Returns:
        coverage: (N, H, W) in [0, 1].
        jvp: (N, M, H, W) derivative of the coverage along each direction.
    """
    count, parts, edges = lines.shape[:3]
    directions = tangents.shape[1]
    if tangents.shape != (count, directions, parts, edges, 3):
        raise ValueError(f"tangents must have shape (N, M, P, K, 3) = ({count}, M, {parts}, {edges}, 3), "
                         f"got {tuple(tangents.shape)}")
    inv_sigma = 1.0 / sigma
    basis = _basis(height, width, lines)
    step = _chunk_size(lines, height, width, budget // 3)  # the features hold 3 values per edge
    coverage, jvp = [], []
    for i in range(0, count, step):
        dist, arg = _distances(lines[i:i + step], height, width)  # (n, P, H, W)
        outside = torch.sigmoid(dist * inv_sigma)
        coverage.append(1.0 - outside.prod(dim=1))
        slope = -(outside.prod(dim=1, keepdim=True) * (1 - outside) * inv_sigma)  # d cov / d dist_p
        # features: slope at the attaining edge times (col, row, 1), zero at the others
        features = (_at_edges(slope, arg, edges).unsqueeze(3) * basis).flatten(1, 3)  # (n, P*K*3, HW)
        jvp.append(torch.bmm(tangents[i:i + step].flatten(2), features))  # (n, M, HW)
    if not coverage:
        return lines.new_zeros(0, height, width), lines.new_zeros(0, directions, height, width)
    return torch.cat(coverage), torch.cat(jvp).reshape(count, directions, height, width)


def silhouette_lines(mesh: RenderMesh, camera: Camera, rot: Tensor, trans: Tensor, windows: Tensor,
                     distort: Callable[[Tensor], Tensor] | None = None,
                     shutter: Shutter | None = None) -> Tensor:
    """(B, T, P, K, 3) edge lines of posed shapes in their crop windows (crop pixels).

    The geometry half of :func:`render_silhouettes` (same arguments); the pixel half is
    :func:`coverage_from_lines` or :func:`coverage_jvp` on the flattened ``(B*T, P, K, 3)``.
    """
    batch, frames = rot.shape[:2]
    if shutter is not None:  # (B, T, 3) motion -> the (B*T, 3) of the flattened poses
        shutter = Shutter(shutter.delay, shutter.velocity.reshape(-1, 3), shutter.angular_velocity.reshape(-1, 3))
    lines = contour_lines(mesh, camera, rot.reshape(-1, 3, 3), trans.reshape(-1, 3), distort, shutter)
    lines = window_lines(lines, windows.reshape(-1, 3))
    return lines.reshape(batch, frames, *lines.shape[1:])


def render_silhouettes(
    mesh: RenderMesh,
    camera: Camera,
    rot: Tensor,
    trans: Tensor,
    windows: Tensor,
    *,
    size: tuple[int, int],
    sigma: float | None,
    budget: int = 1 << 21,
    distort: Callable[[Tensor], Tensor] | None = None,
    shutter: Shutter | None = None,
) -> Tensor:
    """Soft silhouettes by sigmoid edges of a shape's convex parts, one crop window per image.

    Args:
        mesh: the shape's convex parts (:meth:`RenderMesh.from_shape`).
        camera: intrinsics.
        rot: (B, T, 3, 3) rotations ``R`` (mesh to camera).
        trans: (B, T, 3) translations ``t``, metres.
        windows: (B, T, 3) crop windows ``(u0, v0, stride)`` in image pixels (see module doc);
            :func:`full_window` gives the whole image.
        size: crop ``(H, W)`` in pixels.
        sigma: edge width in crop pixels, coverage = sigmoid(-d / sigma); ``None`` renders hard
            (binary) silhouettes without gradients.
        budget: bounds the memory of the pixel loop (elements per chunk).
        distort: optional lens model on normalised coordinates (see :func:`contour_lines`);
            it sees all B·T poses at once, candidate-major (a per-candidate lens such as
            :meth:`torchfit.effects.LensDistortion.distort` with (B,) parameters maps row ``n``
            to candidate ``n // T``).
        shutter: optional rolling shutter (:class:`Shutter`) with (B, T, 3) or (B·T, 3)
            velocities; its ``delay`` sees the B·T poses' rows, candidate-major.

    Returns:
        (B, T, H, W) coverage in [0, 1].
    """
    if rot.dim() != 4 or rot.shape[-2:] != (3, 3):
        raise ValueError(f"rot must have shape (B, T, 3, 3), got {tuple(rot.shape)}")
    batch, frames = rot.shape[:2]
    for name, value in (("trans", trans), ("windows", windows)):
        if tuple(value.shape) != (batch, frames, 3):
            raise ValueError(f"{name} must have shape (B, T, 3) = ({batch}, {frames}, 3), "
                             f"got {tuple(value.shape)}")
    if len(size) != 2 or min(size) < 1:
        raise ValueError(f"size must be (H, W) with positive entries, got {size}")
    if sigma is not None and not (math.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be a positive edge width in pixels or None, got {sigma}")
    lines = silhouette_lines(mesh, camera, rot, trans, windows, distort, shutter).flatten(0, 1)
    coverage = coverage_from_lines(lines, size[0], size[1], sigma=sigma, budget=budget)
    return coverage.reshape(batch, frames, size[0], size[1])


def silhouette_moments(mesh: RenderMesh, camera: Camera, rot: Tensor, trans: Tensor,
                       distort: Callable[[Tensor], Tensor] | None = None, shutter: Shutter | None = None,
                       budget: int = 1 << 20) -> tuple[Tensor, Tensor, Tensor]:
    """Exact area, centroid and second central moments of posed shapes' hard silhouettes.

    No pixels: the silhouette of the union of convex parts is bounded by the pieces of each
    part's contour edges that lie outside every other part, and Green's theorem turns its
    moments into sums over those pieces. A piece from ``p`` to ``q`` (walked anticlockwise in
    (u, v), see :func:`_contour`) adds ``x / (n + 2)`` times the mean of ``u^i v^j`` (``n = i +
    j``) along it to the moment ``m_ij``, with ``x = p_u q_v - q_u p_v``: the 1-form ``u^i v^j
    (u dv - v du) / (n + 2)`` has exterior derivative ``u^i v^j du dv``. Each edge is cut by the
    other parts as parametric intervals (a convex part meets a line in one interval) and the
    pieces outside all of them are kept. Where two parts' edges lie on one line, a tolerance
    keeps exactly one of two edges walked the same way (the lower part's) and neither of two
    walked opposite ways (a seam inside the union). Moments are continuous in the pose: a face
    turning edge-on changes which edges are contour edges, not the polygon.

    Compared with the moments of :func:`render_silhouettes`' pixels this has no sampling error
    and no sigmoid overshoot at corners (see :class:`torchfit.discover_video.VideoProblem`).
    With a lens or a rolling shutter the edges between moved vertices are straight, as there.

    Args:
        mesh, camera, rot (N, 3, 3), trans (N, 3), distort, shutter: as :func:`contour_lines`.
        budget: elements of a chunk's work sets, the (n, P, E, 2) facing test and the (n, P, K,
            P - 1, K) cuts; bounds memory (and keeps them near the cache: 2^20 measured fastest
            of 2^16-2^22 on the T-handle).

    Returns:
        area: (N,) pixels² (0 for a shape behind the camera).
        centroid: (N, 2) ``(u, v)`` image pixels.
        covariance: (N, 2, 2) pixels², as :func:`torchfit.losses.mask_moments`.
    """
    if not len(rot):
        return rot.new_zeros(0), rot.new_zeros(0, 2), rot.new_zeros(0, 2, 2)
    # the facing test, the lines and the cuts in chunks of poses, within the budget (40000 ball
    # poses in one chunk ran 1.44 times as long as in chunks, side by side); only the contour
    # edges' ends are projected, all poses at once (:func:`_contour_ends`)
    posed, ends, keep, step = _contour_ends(mesh, camera, rot, trans, distort, shutter, budget)
    pieces = [_moments_of(_lines_of(ends[i:i + step], keep[i:i + step], posed.rows(i, i + step)), budget)
              for i in range(0, len(rot), step)]
    return tuple(torch.cat(piece) for piece in zip(*pieces))


def _moments_of(contour: _Contour, budget: int) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`silhouette_moments` of N poses' contour (:func:`_contour`)."""
    # about a point near each silhouette, the mean of its drawn edges' ends: the second moments do
    # not cancel digits. Only drawn edges: a rolling shutter's contour, each edge decided at its
    # own time, need not close exactly, and then the sum depends on the origin (a mean over every
    # slot made a ball's moments depend on how many slots its chunk of poses had, 1e-4 relative)
    drawn = contour.drawn.to(contour.edges.dtype)[..., None, None]  # (N, P, K, 1, 1)
    origin = ((contour.edges.detach() * drawn).sum(dim=(1, 2, 3))
              / (2 * drawn.sum(dim=(1, 2, 3))).clamp(min=1.0))  # (N, 2)
    edges = contour.edges - origin[:, None, None, None]
    lines = contour.lines
    lines = torch.cat((lines[..., :2], (lines[..., 2] + (lines[..., :2] * origin[:, None, None]).sum(-1)).unsqueeze(-1)), -1)
    parts, per_part = lines.shape[1:3]
    step = max(1, budget // max(parts * per_part * max(parts - 1, 1) * per_part * 2, 1))
    raw = torch.cat([_outside_moments(edges[i:i + step], lines[i:i + step], contour.drawn[i:i + step])
                     for i in range(0, len(edges), step)])
    area, centroid, cov = central_moments(raw)
    return area, centroid + origin, cov


def _outside_moments(edges: Tensor, lines: Tensor, drawn: Tensor) -> Tensor:
    """(N, 6) raw moments ``(m00, m10, m01, m20, m11, m02)`` of the union of convex parts from
    their (N, P, K, 2, 2) walked contour edges, (N, P, K, 3) lines (both about one origin) and
    (N, P, K) drawn flags: Green's theorem over the edges' pieces outside the other parts."""
    parts = lines.shape[1]
    start, end = edges[..., 0, :], edges[..., 1, :]  # (N, P, K, 2)
    if parts > 1:
        # f(t) = n_l . (start + t d) + c_l for every edge (p, k) and every line (q, l) of each of
        # the Q = P - 1 other parts
        d = end - start
        index = torch.arange(parts, device=lines.device)
        others = torch.stack([torch.cat((index[:p], index[p + 1:])) for p in range(parts)])  # (P, Q)
        other = lines[:, others]  # (N, P, Q, L, 3)
        normal = other[..., :2]
        alpha = torch.einsum("npkx,npqlx->npkql", start, normal) + other[..., 2].unsqueeze(2)
        beta = torch.einsum("npkx,npqlx->npkql", d, normal)
        # on a shared line: the lower part keeps an edge walked the same way, a seam is dropped
        lower = (others < index[:, None])[None, :, None, :, None]  # (1, P, 1, Q, 1): q < p
        same_way = torch.einsum("npkx,npqlx->npkql", _perp(d), normal) > 0
        resolution = torch.finfo(lines.dtype).eps
        eps = 1e3 * resolution * (1.0 + start.detach().abs().amax(dim=(1, 2, 3)))[:, None, None, None, None]
        tol = torch.where(lower | ~same_way, eps, -eps)
        slack = tol - alpha  # inside part q where beta t <= slack for all its lines
        tiny = beta.abs() <= 10 * resolution * (1.0 + d.detach().norm(dim=-1))[..., None, None]
        safe_beta = torch.where(tiny, torch.ones_like(beta), beta)
        bound = slack / safe_beta
        inf = torch.full_like(bound, math.inf)
        lo = torch.where(~tiny & (beta < 0), bound, -inf).amax(-1).clamp(min=0.0)  # (N, P, K, Q)
        hi = torch.where(~tiny & (beta > 0), bound, inf).amin(-1).clamp(max=1.0)
        feasible = ~(tiny & (slack < 0)).any(-1) & (lo < hi)
        one = torch.ones_like(lo)
        lo, hi = torch.where(feasible, lo, one), torch.where(feasible, hi, one)
        # sweep each edge's [0, 1] over the other parts' intervals: pieces where none covers it
        cuts, order = torch.sort(torch.cat((lo, hi), -1), dim=-1)  # (N, P, K, 2Q)
        steps = torch.cat((torch.ones_like(lo), -torch.ones_like(hi)), -1).gather(-1, order)
        covered = torch.cat((torch.zeros_like(steps[..., :1]), steps.cumsum(-1)), -1)  # (N, P, K, 2Q + 1)
        knots = torch.cat((torch.zeros_like(cuts[..., :1]), cuts, torch.ones_like(cuts[..., :1])), -1)
        points = start.unsqueeze(-2) + knots.unsqueeze(-1) * d.unsqueeze(-2)  # (N, P, K, 2Q + 2, 2)
        start, end = points[..., :-1, :], points[..., 1:, :]
        keep = drawn.unsqueeze(-1) & (covered.round() == 0)
    else:
        start, end, keep = start.unsqueeze(-2), end.unsqueeze(-2), drawn.unsqueeze(-1)
    pu, pv, qu, qv = start[..., 0], start[..., 1], end[..., 0], end[..., 1]
    cross = torch.where(keep, pu * qv - qu * pv, torch.zeros_like(pu))
    terms = torch.stack((cross / 2, cross * (pu + qu) / 6, cross * (pv + qv) / 6,
                         cross * (pu * pu + pu * qu + qu * qu) / 12,
                         cross * (2 * pu * pv + pu * qv + qu * pv + 2 * qu * qv) / 24,
                         cross * (pv * pv + pv * qv + qv * qv) / 12), -1)
    return terms.flatten(1, -2).sum(1)


def _perp(d: Tensor) -> Tensor:
    """(..., 2) the outward normal direction ``(dv, -du)`` of edges walked along ``d``."""
    return torch.stack((d[..., 1], -d[..., 0]), -1)


def full_window(camera: Camera, *shape: int, dtype=torch.float32, device="cpu") -> Tensor:
    """(*shape, 3) windows covering the whole image at one crop pixel per image pixel."""
    return torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device).expand(*shape, 3)


def crop_windows(boxes: Tensor, size: tuple[int, int], margin: float = 0.25) -> Tensor:
    """Windows centred on boxes, scaled so the box plus a margin fills the crop.

    Args:
        boxes: (..., 4) ``(u_min, v_min, u_max, v_max)``, image pixels.
        size: crop ``(H, W)``.
        margin: extra fraction of the box's larger side on each side.

    Returns:
        (..., 3) windows ``(u0, v0, stride)``.
    """
    height, width = size
    centre_u = 0.5 * (boxes[..., 0] + boxes[..., 2])
    centre_v = 0.5 * (boxes[..., 1] + boxes[..., 3])
    extent = torch.maximum(boxes[..., 2] - boxes[..., 0], boxes[..., 3] - boxes[..., 1])
    stride = (extent * (1 + 2 * margin)).clamp(min=1.0) / max(height, width)
    u0 = centre_u - stride * (width - 1) / 2
    v0 = centre_v - stride * (height - 1) / 2
    return torch.stack((u0, v0, stride), dim=-1)
