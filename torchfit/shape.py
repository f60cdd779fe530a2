"""Shapes: meshes, mass properties, rotational symmetry and the convex parts the renderer draws.

A :class:`Shape` bundles what the rest of torchfit needs to know about the thrown object:
its mesh (metres, the user's own coordinates), mass, centre of mass and inertia tensor about the
centre of mass (mesh axes), the rotations that map it onto itself, and a render representation
as a union of convex parts (see :mod:`torchfit.render` for why convex parts).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = ["Shape", "ConvexPart", "PRIMITIVES", "make_shape", "load_shape", "primitive_parts"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ConvexPart:
    """One convex piece of the render representation, ready for contour extraction.

    A part's silhouette is the projection of its contour edges: the edges whose two adjacent
    faces face the camera differently. A flat triangle is the degenerate case with two opposite
    faces, so every edge is a contour edge.

    Attributes:
        vertices: (Vp, 3) float64, mesh coordinates, metres.
        edges: (E, 2) int64 vertex indices into ``vertices``.
        edge_normals: (E, 2, 3) unit outward normals of the two faces adjacent to each edge.
        edge_offsets: (E, 2) plane offsets ``n · x`` of those faces.
        centroid: (3,) a point strictly inside the part (mean of its vertices).
        edge_facets: (E, 2) int64 the facet (a maximal group of coplanar faces) of each of those
            faces, indices into ``facet_weights``.
        facet_weights: (F, Vp) float64 each facet's boundary vertices, each weighted one over
            their count: a facet's row delay under a rolling shutter is the weighted sum of its
            vertices', the same for every edge that borders it.
    """

    vertices: np.ndarray
    edges: np.ndarray
    edge_normals: np.ndarray
    edge_offsets: np.ndarray
    centroid: np.ndarray
    edge_facets: np.ndarray
    facet_weights: np.ndarray

    @staticmethod
    def from_convex_mesh(mesh: trimesh.Trimesh, angle_tol: float = 1e-6) -> "ConvexPart":
        """Build from a closed convex mesh; edges between coplanar faces are dropped."""
        adjacency = mesh.face_adjacency  # (E, 2) face pairs
        keep = mesh.face_adjacency_angles > angle_tol
        faces = adjacency[keep]
        edges = mesh.face_adjacency_edges[keep]
        normals = mesh.face_normals[faces]  # (E, 2, 3)
        points = mesh.vertices[mesh.faces[faces][..., 0]]  # (E, 2, 3) a vertex of each face
        offsets = np.einsum("efk,efk->ef", normals, points)
        used, edges = np.unique(edges, return_inverse=True)
        edges = edges.reshape(-1, 2)
        vertices = np.asarray(mesh.vertices[used], dtype=np.float64)
        # facets: the faces joined across the coplanar adjacencies dropped above
        joined = adjacency[~keep]
        graph = coo_matrix((np.ones(len(joined)), (joined[:, 0], joined[:, 1])), shape=(len(mesh.faces),) * 2)
        _, facet_of = connected_components(graph, directed=False)
        edge_facets = np.unique(facet_of, return_inverse=True)[1][faces].reshape(-1, 2)
        return ConvexPart(vertices, edges.astype(np.int64), normals, offsets, vertices.mean(0),
                          edge_facets.astype(np.int64), _facet_weights(edges, edge_facets, len(vertices)))

    @staticmethod
    def from_triangle(triangle: np.ndarray) -> "ConvexPart":
        """A flat triangle (3, 3) seen from both sides: all three edges are always contour."""
        a, b, c = triangle
        normal = np.cross(b - a, c - a)
        normal = normal / max(np.linalg.norm(normal), 1e-300)
        edges = np.array([[0, 1], [1, 2], [2, 0]], dtype=np.int64)
        normals = np.broadcast_to(np.stack([normal, -normal]), (3, 2, 3)).copy()
        offsets = np.broadcast_to(np.array([normal @ a, -(normal @ a)]), (3, 2)).copy()
        edge_facets = np.broadcast_to(np.array([0, 1], dtype=np.int64), (3, 2)).copy()
        return ConvexPart(np.asarray(triangle, np.float64), edges, normals, offsets, triangle.mean(0),
                          edge_facets, _facet_weights(edges, edge_facets, 3))


def _facet_weights(edges: np.ndarray, edge_facets: np.ndarray, vertices: int) -> np.ndarray:
    """(F, V) each facet's boundary vertices (the ends of the (E, 2) ``edges`` that border it,
    ``edge_facets`` (E, 2)), each weighted one over their count."""
    weights = np.zeros((int(edge_facets.max()) + 1, vertices))
    for side in range(2):
        weights[edge_facets[:, side, None], edges] = 1.0
    return weights / np.maximum(weights.sum(1, keepdims=True), 1.0)


@dataclass(frozen=True)
class Shape:
    """A rigid object of known shape and mass distribution.

    Attributes:
        name: primitive name or mesh file stem.
        mesh: the mass mesh, metres, in the user's mesh coordinates.
        mass: kg.
        com: (3,) centre of mass, mesh coordinates, metres.
        inertia: (3, 3) inertia tensor about the centre of mass, mesh axes, kg m^2.
        parts: convex parts whose union is the silhouette-relevant shape.
        symmetries: (K, 3, 3) proper rotations ``S`` about the centre of mass with
            ``S (X - com) + com`` mapping the shape onto itself; ``symmetries[0]`` is the identity.
    """

    name: str
    mesh: trimesh.Trimesh
    mass: float
    com: np.ndarray
    inertia: np.ndarray
    parts: tuple[ConvexPart, ...]
    symmetries: np.ndarray = field(repr=False)

    @property
    def principal_moments(self) -> np.ndarray:
        """(3,) principal moments of inertia, ascending, kg m^2."""
        return np.linalg.eigvalsh(self.inertia)

    @property
    def principal_axes(self) -> np.ndarray:
        """(3, 3) principal axes as columns (mesh coordinates), matching ``principal_moments``."""
        return np.linalg.eigh(self.inertia)[1]

    @property
    def volume(self) -> float:
        """Volume of the mass mesh, m^3."""
        return float(self.mesh.volume)

    @property
    def reference_area(self) -> float:
        """Mean projected area of the convex hull (Cauchy: a quarter of its surface), m^2."""
        return float(self.mesh.convex_hull.area) / 4.0

    @property
    def round(self) -> bool:
        """True for a sphere about its centre of mass: the mesh fills at least 95 % of the ball
        through its farthest vertex (an icosphere of 162 vertices fills 96.6 %, of 642 99.1 %; a
        cube 37 %, a cylinder as tall as it is wide 53 %). No rotation changes its silhouette, so
        its orientation and spin are hidden from video; it is drawn as its sphere, not its mesh
        (:attr:`torchfit.render.RenderMesh.sphere`)."""
        return bool(self.volume >= 0.95 * 4.0 / 3.0 * np.pi * self.radius**3)

    @property
    def radius(self) -> float:
        """Largest distance of a vertex from the centre of mass, metres."""
        return float(np.linalg.norm(self.mesh.vertices - self.com, axis=1).max())


# ---------------------------------------------------------------------------------------------
# primitives


def _box(extents, center=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_translation(center)
    return mesh


def _positive(name: str, value) -> float:
    value = float(value)
    if not np.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive length in metres, got {value}")
    return value


def _tshape(crossbar_length=0.20, stem_length=0.15, thickness=0.03):
    """T-handle: crossbar along x centred at the origin, stem along +y below it (image-down)."""
    length, stem, thick = (_positive(n, v) for n, v in
                           (("crossbar_length", crossbar_length), ("stem_length", stem_length),
                            ("thickness", thickness)))
    crossbar = _box((length, thick, thick))
    stem_mesh = _box((thick, stem, thick), (0.0, thick / 2 + stem / 2, 0.0))
    mass_mesh = trimesh.util.concatenate([crossbar, stem_mesh])
    # The render stem reaches into the crossbar so the two parts overlap rather than abut: a soft
    # union of two parts that only touch along a line would leave a half-covered seam.
    render_stem = _box((thick, stem + thick / 2, thick), (0.0, stem / 2 + thick / 4, 0.0))
    return mass_mesh, [crossbar, render_stem]


def _box_primitive(extents=(0.12, 0.08, 0.05)):
    extents = [_positive("extents", e) for e in extents]
    if len(extents) != 3:
        raise ValueError(f"box extents must have 3 values, got {len(extents)}")
    mesh = _box(extents)
    return mesh, [mesh]


def _cylinder(radius=0.035, height=0.22, sections=32):
    mesh = trimesh.creation.cylinder(radius=_positive("radius", radius),
                                     height=_positive("height", height), sections=int(sections))
    return mesh, [mesh]


def _sphere(radius=0.02, subdivisions=2):
    mesh = trimesh.creation.icosphere(subdivisions=int(subdivisions),
                                      radius=_positive("radius", radius))
    return mesh, [mesh]


PRIMITIVES = {"tshape": _tshape, "box": _box_primitive, "cylinder": _cylinder, "sphere": _sphere}


def primitive_parts(name: str, **dims) -> tuple[trimesh.Trimesh, list[trimesh.Trimesh]]:
    """Mass mesh and convex render meshes of a built-in primitive.

    Raises:
        ValueError: unknown name, or a dimension that is not a positive length.
    """
    if name not in PRIMITIVES:
        raise ValueError(f'Invalid primitive "{name}". Must be one of {sorted(PRIMITIVES)}')
    try:
        return PRIMITIVES[name](**dims)
    except TypeError as err:
        raise ValueError(f"bad dimensions for primitive {name!r}: {err}") from None


# ---------------------------------------------------------------------------------------------
# building shapes


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """Read a mesh file (any format trimesh reads) as one triangle mesh.

    Raises:
        ValueError: the file is missing, unreadable, or holds no triangles.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"mesh file {str(path)!r} does not exist")
    try:
        loaded = trimesh.load(path, force="mesh", process=True)
    except Exception as err:  # trimesh raises many types for bad files
        raise ValueError(f"could not read mesh file {str(path)!r}: {err}") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ValueError(f"mesh file {str(path)!r} holds no triangles")
    return loaded


def _reduce_convex(mesh: trimesh.Trimesh, max_vertices: int) -> trimesh.Trimesh:
    """Convex hull, with its vertex count cut by farthest-point sampling when above the limit."""
    hull = mesh.convex_hull
    if len(hull.vertices) <= max_vertices:
        return hull
    points = np.asarray(hull.vertices)
    chosen = [int(np.argmax(np.linalg.norm(points - points.mean(0), axis=1)))]
    dist = np.linalg.norm(points - points[chosen[0]], axis=1)
    while len(chosen) < max_vertices:
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(points - points[chosen[-1]], axis=1))
    reduced = trimesh.convex.convex_hull(points[chosen])
    # an inscribed hull is smaller: scale it about its centre to the full hull's volume
    centre = reduced.center_mass
    reduced.apply_translation(-centre)
    reduced.apply_scale((hull.volume / reduced.volume) ** (1.0 / 3.0))
    reduced.apply_translation(centre)
    return reduced


def _is_convex(mesh: trimesh.Trimesh) -> bool:
    return mesh.is_watertight and abs(mesh.convex_hull.volume - mesh.volume) <= 1e-3 * mesh.convex_hull.volume


def _render_parts(mesh: trimesh.Trimesh, max_triangles: int) -> list[trimesh.Trimesh]:
    """Convex pieces whose union is the mesh: its convex bodies, else a decomposition of each."""
    bodies = mesh.split(only_watertight=False) if mesh.body_count > 1 else [mesh]
    parts: list[trimesh.Trimesh] = []
    for body in bodies:
        if _is_convex(body):
            parts.append(body)
            continue
        try:  # approximate convex decomposition needs the optional package vhacdx
            pieces = body.convex_decomposition()
            pieces = pieces if isinstance(pieces, list) else [pieces]
            pieces = [trimesh.Trimesh(**p) if isinstance(p, dict) else p for p in pieces]
            log.info("non-convex body: rendering %d convex pieces (V-HACD)", len(pieces))
            parts.extend(pieces)
        except Exception as err:  # noqa: BLE001 - any failure falls back to triangles, logged
            if len(body.faces) > max_triangles:
                raise ValueError(
                    f"non-convex mesh with {len(body.faces)} triangles and no convex decomposition "
                    f"({err}); install vhacdx or simplify the mesh below {max_triangles} triangles"
                ) from None
            log.warning("non-convex mesh and no convex decomposition (%s): rendering its %d "
                        "triangles one by one (slower, and soft edges bleed at sliver corners)",
                        err, len(body.faces))
            parts.extend(trimesh.Trimesh(body.vertices[f], [[0, 1, 2]], process=False) for f in body.faces)
    return parts


def make_shape(
    mesh: trimesh.Trimesh,
    *,
    name: str = "mesh",
    density: float | None = None,
    mass: float | None = None,
    com=None,
    inertia=None,
    render_meshes: list[trimesh.Trimesh] | None = None,
    hull_fallback: bool = False,
    max_part_vertices: int = 256,
    max_triangles: int = 512,
) -> Shape:
    """A :class:`Shape` from a mass mesh and either a density or a mass.

    Args:
        mesh: watertight triangle mesh, metres.
        name: label for reports.
        density: kg/m^3; exactly one of ``density`` and ``mass`` must be given.
        mass: kg.
        com: optional (3,) centre of mass overriding the uniform-density one, mesh coordinates.
        inertia: optional (3, 3) inertia about the centre of mass, mesh axes, overriding.
        render_meshes: convex meshes whose union is the shape; computed when omitted.
        hull_fallback: a mesh that is not watertight uses its convex hull for mass properties
            (logged) instead of raising.
        max_part_vertices: convex parts with more hull vertices are reduced to this many.
        max_triangles: the most triangles rendered one by one when no decomposition exists.

    Raises:
        ValueError: bad mass or density, a mesh that is not watertight (unless ``hull_fallback``),
            or an inertia that is not symmetric positive definite.
    """
    if (density is None) == (mass is None):
        raise ValueError(f"give exactly one of density and mass, got density={density}, mass={mass}")
    for label, value in (("density", density), ("mass", mass)):
        if value is not None and (not np.isfinite(float(value)) or float(value) <= 0):
            raise ValueError(f"{label} must be positive, got {value}")
    mass_mesh = mesh
    if not mesh.is_watertight:
        if not hull_fallback:
            raise ValueError(
                f"mesh {name!r} is not watertight, so its volume and inertia are undefined; "
                "repair it, or set hull_fallback to use its convex hull"
            )
        log.warning("mesh %r is not watertight: mass properties from its convex hull", name)
        mass_mesh = mesh.convex_hull
    volume = float(mass_mesh.volume)
    if not volume > 0:
        raise ValueError(f"mesh {name!r} has non-positive volume {volume} (inverted faces?)")
    rho = float(density) if density is not None else float(mass) / volume
    total = rho * volume
    center = np.asarray(mass_mesh.center_mass, dtype=np.float64)
    tensor = np.asarray(mass_mesh.moment_inertia, dtype=np.float64) * rho  # trimesh: density 1
    if com is not None:
        new_com = np.asarray(com, dtype=np.float64).reshape(3)
        # parallel-axis shift keeps the given body's inertia about the new centre consistent
        tensor = tensor + total * _parallel_axis(center) - total * _parallel_axis(new_com)
        center = new_com
    if inertia is not None:
        tensor = np.asarray(inertia, dtype=np.float64)
        if tensor.shape != (3, 3):
            raise ValueError(f"inertia must have shape (3, 3), got {tensor.shape}")
    if not np.allclose(tensor, tensor.T, rtol=1e-6, atol=1e-12) or np.linalg.eigvalsh(tensor).min() <= 0:
        raise ValueError(f"inertia must be symmetric positive definite, got {tensor.tolist()}")
    meshes = render_meshes if render_meshes is not None else _render_parts(
        mesh if mesh.is_watertight else mesh.convex_hull, max_triangles)
    parts = []
    for piece in meshes:
        if len(piece.faces) == 1:
            parts.append(ConvexPart.from_triangle(np.asarray(piece.vertices[piece.faces[0]], np.float64)))
        else:
            parts.append(ConvexPart.from_convex_mesh(_reduce_convex(piece, max_part_vertices)))
    symmetries = find_symmetries(mesh, center, tensor)
    return Shape(name, mesh, total, center, tensor, tuple(parts), symmetries)


def _parallel_axis(offset: np.ndarray) -> np.ndarray:
    return float(offset @ offset) * np.eye(3) - np.outer(offset, offset)


def load_shape(
    mesh: str | Path | None = None,
    *,
    primitive: str | None = None,
    dims: dict | None = None,
    **mass_kwargs,
) -> Shape:
    """A shape from a mesh file or a primitive name (exactly one), plus mass properties.

    Args:
        mesh: path of a mesh file.
        primitive: one of ``PRIMITIVES``.
        dims: the primitive's dimensions, metres (e.g. ``{"radius": 0.02}``).
        **mass_kwargs: passed to :func:`make_shape` (density or mass, com, inertia, ...).
    """
    if (mesh is None) == (primitive is None):
        raise ValueError(f"give exactly one of mesh and primitive, got mesh={mesh}, primitive={primitive}")
    if primitive is not None:
        mass_mesh, render = primitive_parts(primitive, **(dims or {}))
        return make_shape(mass_mesh, name=primitive, render_meshes=render, **mass_kwargs)
    return make_shape(load_mesh(mesh), name=Path(mesh).stem, **mass_kwargs)


# ---------------------------------------------------------------------------------------------
# symmetry


def find_symmetries(mesh: trimesh.Trimesh, com: np.ndarray, inertia: np.ndarray,
                    tol: float = 1e-4) -> np.ndarray:
    """Proper rotations about the centre of mass that map the mesh onto itself.

    Candidates come from pairs of vertices (Kabsch on two vertex pairs with matching distances
    from the centre); a candidate is kept when it preserves the inertia tensor, maps the vertex
    set onto itself and keeps every face centre on the surface, all within ``tol`` times the
    shape's size.

    Returns:
        (K, 3, 3) rotations, identity first.
    """
    points = np.unique(np.round(np.asarray(mesh.vertices) - com, 12), axis=0)
    scale = np.linalg.norm(points, axis=1).max()
    atol = tol * scale
    tree = cKDTree(points)
    radii = np.linalg.norm(points, axis=1)
    order = np.argsort(-radii)
    first = points[order[0]]
    # second anchor: the farthest vertex not collinear with the first (through the centre)
    second = None
    for idx in order[1:]:
        if np.linalg.norm(np.cross(first, points[idx])) > 1e-3 * scale * radii[idx]:
            second = points[idx]
            break
    found = [np.eye(3)]
    if second is None:  # all vertices on a line: only the identity is checked
        return np.stack(found)
    anchors = np.stack([first, second, np.cross(first, second)])
    cand1 = np.flatnonzero(np.abs(radii - np.linalg.norm(first)) < atol)
    cand2 = np.flatnonzero(np.abs(radii - np.linalg.norm(second)) < atol)
    face_centres = np.asarray(mesh.triangles_center) - com
    inertia_scale = np.abs(inertia).max()
    pairs = [(i, j) for i in cand1 for j in cand2[np.abs(points[cand2] @ points[i] - first @ second)
                                                   <= atol * scale]]
    for i, j in pairs:
        target = np.stack([points[i], points[j], np.cross(points[i], points[j])])
        rot = _kabsch(anchors, target)
        if np.linalg.det(rot) < 0 or np.abs(rot @ inertia @ rot.T - inertia).max() > 1e-4 * inertia_scale:
            continue
        if any(np.abs(rot - f).max() < 1e-6 for f in found):
            continue
        if tree.query(points @ rot.T)[0].max() > atol:
            continue
        moved = face_centres @ rot.T + com
        _, dist, _ = trimesh.proximity.closest_point(mesh, moved)
        if dist.max() > atol:
            continue
        found.append(rot)
    return np.stack(found)


def _kabsch(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Rotation R minimising |R source_i - target_i| for (N, 3) point sets through the origin."""
    u, _, vt = np.linalg.svd(target.T @ source)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt
