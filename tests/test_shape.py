import logging

import numpy as np
import pytest
import trimesh

from torchfit.shape import PRIMITIVES, load_mesh, load_shape, make_shape


def test_box_mass_properties_match_closed_form():
    a, b, c, rho = 0.12, 0.08, 0.05, 600.0
    shape = load_shape(primitive="box", dims={"extents": (a, b, c)}, density=rho)
    mass = rho * a * b * c
    assert shape.mass == pytest.approx(mass, rel=1e-12)
    np.testing.assert_allclose(shape.com, 0.0, atol=1e-12)
    expected = mass / 12 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])
    np.testing.assert_allclose(shape.inertia, expected, rtol=1e-9, atol=1e-15)


def test_cylinder_mass_properties_match_closed_form():
    # the mesh is a regular n-gon prism: closed form from n isosceles triangles about the axis
    r, h, n, rho = 0.035, 0.22, 32, 600.0
    shape = load_shape(primitive="cylinder", dims={"radius": r, "height": h, "sections": n}, density=rho)
    theta = 2 * np.pi / n
    mass = rho * h * n * 0.5 * r * r * np.sin(theta)
    assert shape.mass == pytest.approx(mass, rel=1e-9)
    axial = mass * r * r * (2 + np.cos(theta)) / 6
    transverse = axial / 2 + mass * h * h / 12
    np.testing.assert_allclose(shape.inertia, np.diag([transverse, transverse, axial]), rtol=1e-9, atol=1e-15)


def test_mass_given_instead_of_density_scales_inertia():
    by_density = load_shape(primitive="box", density=600.0)
    by_mass = load_shape(primitive="box", mass=2 * by_density.mass)
    np.testing.assert_allclose(by_mass.inertia, 2 * by_density.inertia, rtol=1e-12)


def test_tshape_mass_properties_and_symmetry_group():
    shape = load_shape(primitive="tshape", density=600.0)
    # crossbar 0.2 x 0.03 x 0.03 at the origin, stem 0.03 x 0.15 x 0.03 below it
    crossbar, stem = 600 * 0.2 * 0.03 * 0.03, 600 * 0.03 * 0.15 * 0.03
    assert shape.mass == pytest.approx(crossbar + stem, rel=1e-12)
    assert shape.com[1] == pytest.approx(stem * (0.015 + 0.075) / (crossbar + stem), rel=1e-9)
    sym = shape.symmetries
    assert sym.shape == (2, 3, 3)
    np.testing.assert_allclose(sym[0], np.eye(3), atol=1e-12)
    # the other one is the half turn about the stem (y) axis
    np.testing.assert_allclose(sym[1], np.diag([-1.0, 1.0, -1.0]), atol=1e-9)


@pytest.mark.parametrize("name, order", [("box", 4), ("cylinder", 64), ("sphere", 60)])
def test_symmetry_group_orders(name, order):
    shape = load_shape(primitive=name, density=600.0)
    assert len(shape.symmetries) == order
    for rot in shape.symmetries:
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(rot) == pytest.approx(1.0)


def test_render_parts_are_convex_pieces():
    shape = load_shape(primitive="tshape", density=600.0)
    assert len(shape.parts) == 2
    for part in shape.parts:
        assert len(part.vertices) == 8 and len(part.edges) == 12


def test_mesh_file_roundtrip(tmp_path):
    path = tmp_path / "thing.obj"
    trimesh.creation.box(extents=(0.1, 0.2, 0.3)).export(path)
    shape = load_shape(path, density=1000.0)
    assert shape.name == "thing"
    assert shape.mass == pytest.approx(1000 * 0.006, rel=1e-9)


def test_non_convex_mesh_renders_as_pieces_or_triangles(tmp_path, caplog):
    mesh = trimesh.util.concatenate([trimesh.creation.box(extents=(0.2, 0.03, 0.03)),
                                     trimesh.creation.box(extents=(0.03, 0.2, 0.03),
                                                          transform=trimesh.transformations.translation_matrix((0.0, 0.115, 0.0)))])
    with caplog.at_level(logging.INFO):
        shape = make_shape(mesh, density=600.0)
    assert len(shape.parts) >= 2


def test_bad_inputs_raise_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="density must be positive"):
        load_shape(primitive="box", density=-1.0)
    with pytest.raises(ValueError, match="exactly one of density and mass"):
        load_shape(primitive="box")
    with pytest.raises(ValueError, match="does not exist"):
        load_mesh(tmp_path / "missing.obj")
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(b"\x00\x01 not a mesh at all")
    with pytest.raises(ValueError, match="garbage.stl"):
        load_mesh(garbage)
    with pytest.raises(ValueError, match="Invalid primitive"):
        load_shape(primitive="banana", density=1.0)
    with pytest.raises(ValueError, match="positive length"):
        load_shape(primitive="sphere", dims={"radius": 0.0}, density=1.0)
    with pytest.raises(ValueError, match="symmetric positive definite"):
        load_shape(primitive="box", density=600.0, inertia=-np.eye(3))


def test_open_mesh_needs_explicit_hull_fallback(caplog):
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    open_mesh = trimesh.Trimesh(box.vertices, box.faces[:-2])
    with pytest.raises(ValueError, match="not watertight"):
        make_shape(open_mesh, density=600.0)
    with caplog.at_level(logging.WARNING):
        shape = make_shape(open_mesh, density=600.0, hull_fallback=True)
    assert "convex hull" in caplog.text
    assert shape.mass == pytest.approx(0.6, rel=1e-9)


def test_every_primitive_builds():
    for name in PRIMITIVES:
        assert load_shape(primitive=name, density=500.0).mass > 0


@pytest.mark.parametrize("name, dims, facets, sizes", [
    ("box", {}, 6, {4}),
    ("cylinder", {"sections": 32}, 34, {4, 32}),
    ("sphere", {"subdivisions": 2}, 320, {3}),
])
def test_convex_parts_know_each_edges_facets(name, dims, facets, sizes):
    """Each contour-candidate edge names the facets (maximal coplanar face groups) either side of
    it, and each facet's weights are one over its boundary vertices: a box's 6 quads, a
    cylinder's 32 side quads and two 32-gon caps (their triangles joined), an icosphere's
    triangles. The two facets of an edge differ, and its ends are on both."""
    part = load_shape(primitive=name, dims=dims, density=500.0).parts[0]
    weights = part.facet_weights
    assert weights.shape == (facets, len(part.vertices))
    assert set((weights > 0).sum(1).tolist()) == sizes
    np.testing.assert_allclose(weights.sum(1), 1.0)
    assert np.all(part.edge_facets[:, 0] != part.edge_facets[:, 1])
    for side in range(2):
        assert np.all(weights[part.edge_facets[:, side, None], part.edges] > 0)

