"""Procedural meshes: closed, outward-facing, the documented conventions."""
import time

import numpy as np
import pytest
import trimesh

from dosppm_core.scene import shapes


def _mesh(vertices, faces):
    return trimesh.Trimesh(vertices, faces, process=False)


def _normals(vertices, faces):
    v = vertices[faces]
    return np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])


CLOSED = {
    "box": shapes.box,
    "ico_sphere_0": lambda: shapes.ico_sphere(0),
    "ico_sphere_4": lambda: shapes.ico_sphere(4),
    "uv_sphere": lambda: shapes.uv_sphere(16, 32),
    "uv_sphere_coarse": lambda: shapes.uv_sphere(2, 3),
    "torus_knot_small": lambda: shapes.torus_knot(tubular_segments=64, radial_segments=8),
}


@pytest.mark.parametrize("name", CLOSED)
def test_closed_shapes_are_watertight_and_outward(name):
    vertices, faces = CLOSED[name]()
    assert vertices.dtype == np.float64 and vertices.shape[1] == 3
    assert faces.shape[1] == 3 and np.issubdtype(faces.dtype, np.integer)
    mesh = _mesh(vertices, faces)
    assert mesh.is_watertight
    assert mesh.is_winding_consistent
    assert mesh.volume > 0  # outward winding gives a positive signed volume


def test_rectangle_is_mitsubas_unit_square_facing_plus_z():
    vertices, faces = shapes.rectangle()
    assert np.array_equal(vertices[:, 2], np.zeros(4))
    assert np.array_equal(vertices[:, :2].min(0), [-1, -1])
    assert np.array_equal(vertices[:, :2].max(0), [1, 1])
    n = _normals(vertices, faces)
    assert np.all(n[:, 2] > 0) and np.allclose(n[:, :2], 0)
    assert _mesh(vertices, faces).area == pytest.approx(4.0)


def test_box_is_the_cube_with_each_face_pointing_away_from_the_centre():
    vertices, faces = shapes.box()
    assert np.array_equal(np.abs(vertices), np.ones((8, 3)))
    n = _normals(vertices, faces)
    centroids = vertices[faces].mean(axis=1)
    assert np.all(np.sum(n * centroids, axis=1) > 0)
    assert _mesh(vertices, faces).volume == pytest.approx(8.0)


@pytest.mark.parametrize("subdivisions", [0, 1, 3, 5])
def test_ico_sphere_is_unit_and_has_expected_count(subdivisions):
    vertices, faces = shapes.ico_sphere(subdivisions)
    assert len(faces) == 20 * 4 ** subdivisions
    assert np.allclose(np.linalg.norm(vertices, axis=1), 1.0)
    # Euler characteristic of a sphere, so no duplicated midpoints.
    assert len(vertices) - len(faces) * 3 // 2 + len(faces) == 2


def test_spheres_approach_the_unit_ball_volume():
    for vertices, faces in (shapes.ico_sphere(5), shapes.uv_sphere(64, 128)):
        volume = _mesh(vertices, faces).volume
        assert volume == pytest.approx(4 / 3 * np.pi, rel=2e-3)
        assert volume < 4 / 3 * np.pi  # inscribed polyhedron


def test_uv_sphere_has_no_degenerate_triangles():
    vertices, faces = shapes.uv_sphere(8, 12)
    assert len(faces) == 2 * 12 * (8 - 1)
    assert np.linalg.norm(_normals(vertices, faces), axis=1).min() > 1e-6


def test_bad_tessellation_arguments_are_rejected():
    with pytest.raises(ValueError):
        shapes.ico_sphere(-1)
    with pytest.raises(ValueError):
        shapes.uv_sphere(1, 8)


def test_glass_knot_is_high_poly_watertight_outward_and_fast():
    start = time.perf_counter()
    vertices, faces = shapes.glass_knot()
    elapsed = time.perf_counter() - start
    assert elapsed < 1.0
    assert len(faces) >= 100_000
    mesh = _mesh(vertices, faces)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.euler_number == 0  # a torus: one closed tube
    # Tube volume ~ pi r^2 * centre-line length (15.95 for the (2,3) knot).
    assert mesh.volume == pytest.approx(np.pi * 0.3 ** 2 * 15.95, rel=0.01)
    assert np.linalg.norm(_normals(vertices, faces), axis=1).min() > 1e-8


def test_glass_knot_is_deterministic():
    a, b = shapes.glass_knot(), shapes.glass_knot()
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_torus_knot_tube_does_not_touch_itself():
    """Every surface point's nearest centre-line point must be at the tube
    radius: a surface point closer to another strand would mean the tube
    intersects itself (refraction would then be wrong)."""
    tube = 0.3
    vertices, _ = shapes.torus_knot(tube_radius=tube, tubular_segments=256, radial_segments=16)
    centre, _ = shapes.torus_knot_curve(np.linspace(0, 2 * np.pi, 6000, endpoint=False))
    for chunk in np.array_split(vertices, 8):
        d = np.linalg.norm(chunk[:, None] - centre[None], axis=2).min(axis=1)
        assert d.min() > tube * 0.99


def test_rotation_matrix_is_right_handed_and_exact_at_quarter_turns():
    r = shapes.rotation_matrix((0, 0, 1), 90)
    assert np.array_equal(r @ [1, 0, 0], [0, 1, 0])  # x turns to y about z
    r = shapes.rotation_matrix((1, 1, 1), 37)
    assert np.allclose(r @ r.T, np.eye(3)) and np.linalg.det(r) == pytest.approx(1)
    assert np.allclose(r @ np.ones(3), np.ones(3))
