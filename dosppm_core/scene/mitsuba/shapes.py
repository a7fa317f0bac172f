"""Shape plugins: obj and ply files, rectangle, cube, sphere (an
icosphere), disk and cylinder (fine polygons), each with to_world,
flip_normals and at most one BSDF and one area emitter; shapegroup and
instance, flattened: each instance adds a moved copy of its group's
triangles.

A shape whose material reads a texture gets texture coordinates laid out
as Mitsuba's: an OBJ's or PLY's own, and for the built-in shapes their
analytic (u, v) at the vertices, with vertices repeated along seams (and
at a sphere's poles and a disk's centre) so that interpolation within a
triangle never crosses from u = 1 back to 0. Other shapes store none.

The front of a surface is its triangle winding (counter-clockwise), which
emission and one-sided BSDFs use and flip_normals reverses. Under a
mirroring to_world Mitsuba keeps the front of rectangles and cubes outward
(so we rewind them) while spheres and meshes turn.

Shading normals are Mitsuba's: an OBJ's or PLY's are interpolated from
its vertex normals (the file's, or computed as Mitsuba does when it has
none: `scene.normals`) unless the shape sets face_normals; spheres and
cylinders, analytic in Mitsuba, get vertex normals whose interpolation
points exactly away from the centre (axis); rectangles, cubes and disks
are flat. The kernels turn an interpolated normal to the winding's side
(Mitsuba would orient by the normals; every shared scene has them
agreeing with the winding)."""
from __future__ import annotations

import functools

import numpy as np

from dosppm_core.scene.mitsuba.attributes import shape_attribute
from dosppm_core.scene.mitsuba.bsdfs import material_id
from dosppm_core.scene.mitsuba.objects import Obj
from dosppm_core.scene.mitsuba.params import (
    finish,
    get_bool,
    get_float,
    get_matrix,
    get_point,
    get_str,
    required,
)
from dosppm_core.scene.mitsuba.state import ReaderState
from dosppm_core.scene.mitsuba.xmltree import Node, resolve
from dosppm_core.scene.normals import COMPUTED, angle_weighted_normals
from dosppm_core.scene.tomlfile import read_mesh_file


# Shapes whose shading normal Mitsuba moves with the inverse transpose of
# to_world, so a mirroring transform keeps their front outward.
MIRROR_KEEPS_FRONT = ("rectangle", "cube", "disk", "cylinder")
GROUPS = ("shapegroup", "instance")
SEGMENTS = 256    # of a disk's rim or a cylinder: the area is short by (2 pi / 256)^2 / 6 = 1e-4


def read_shape(reader: ReaderState, obj: Obj, outer: np.ndarray | None = None) -> None:
    """Add one shape's triangles, with its material, to the builder;
    `outer` is the to_world of the instance a shape group's shape is read
    for (applied after the shape's own)."""
    if obj.type in GROUPS:
        _group_or_instance(reader, obj, outer)
        return
    children = reader.children(obj, {"bsdf", "emitter"})
    bsdf, emitter = reader.single(obj, children, "bsdf"), reader.single(obj, children, "emitter")
    if outer is not None and emitter is not None:
        emitter.node.fail("an emitter inside a shapegroup (Mitsuba does not instance emitters)")
    material = material_id(reader, bsdf, emitter, obj)
    vertices, faces, uv, normals = shape_geometry(reader, obj, reader.builder.textured(material))
    path = _mesh_path(reader, obj) if obj.type in ("obj", "ply") else None
    own = shape_attribute(reader, material, obj, path, vertices, faces)
    if own is not None:
        if isinstance(normals, str):    # the corners come apart: compute Mitsuba's now (in the local frame)
            normals = angle_weighted_normals(vertices, faces)
        normals = None if normals is None else normals[faces].reshape(-1, 3)
        vertices, faces, uv, material = own
    to_world = get_matrix(obj)
    if obj.type == "sphere":
        to_world = _sphere_frame(obj, to_world)
    elif obj.type == "cylinder":
        to_world = _circular(obj, to_world @ _cylinder_frame(obj))
    if outer is not None:
        to_world = outer @ to_world
    if obj.type in MIRROR_KEEPS_FRONT and np.linalg.det(to_world[:3, :3]) < 0:
        # Mitsuba moves these shading normals with the inverse transpose, so
        # a mirror keeps their front outward; its sphere's turns inward.
        faces = faces[:, ::-1]
    if get_bool(obj, "flip_normals", False):
        faces = faces[:, ::-1]
    finish(obj)
    reader.builder.add_mesh(vertices, faces, material, obj.where(), transform=to_world, uv=uv, normals=normals)


def _group_or_instance(reader: ReaderState, obj: Obj, outer) -> None:
    """A shapegroup adds nothing by itself; each instance flattens a copy of
    its shapes into the scene's triangles, moved by the instance's to_world."""
    if outer is not None:
        obj.node.fail(f"a {obj.type} cannot be nested in a shapegroup")
    if obj.type == "shapegroup":
        members = reader.children(obj, {"shape"})
        for member in members:
            if member.type in GROUPS:
                member.node.fail(f"a {member.type} cannot be nested in a shapegroup")
        finish(obj)
        return
    children = reader.children(obj, {"shape"})
    if len(children) != 1 or children[0].type != "shapegroup":
        obj.node.fail("an instance needs exactly one <ref> to a shapegroup")
    to_world = get_matrix(obj)
    finish(obj)
    for member in reader.children(children[0], {"shape"}):
        read_shape(reader, member, to_world)


def shape_geometry(reader: ReaderState, obj: Obj, with_uv: bool = False):
    """(vertices, faces, uv, normals) of a shape in its local frame: a mesh
    file's or one of the built-in shapes'; uv is None unless `with_uv` (and
    the file has some); normals as `SceneBuilder.add_mesh` takes them."""
    if obj.type in ("obj", "ply"):
        flat = get_bool(obj, "face_normals", False)
        vertices, faces, uv, normals = _load_mesh_file(_mesh_path(reader, obj), obj.node)
        if normals is None or not np.any(normals):
            normals = COMPUTED
        return vertices, faces, uv if with_uv else None, None if flat else normals
    if with_uv:
        vertices, faces, uv = _TEXTURED[obj.type]()
    else:
        (vertices, faces), uv = _BUILT_IN[obj.type](), None
    return vertices, faces, uv, _analytic_normals(obj.type, vertices)


def _analytic_normals(kind: str, vertices: np.ndarray):
    """The vertex normals of Mitsuba's analytic shapes, None for flat ones.
    The icosphere's vertices lie on the unit sphere: interpolated, they
    give p - centre at every point p of a triangle, so normalised, the exact
    sphere normal; the cylinder's (x, y, 0) likewise the radial one."""
    if kind == "sphere":
        return vertices.copy()
    if kind == "cylinder":
        return np.c_[vertices[:, :2], np.zeros(len(vertices))]
    return None


def _mesh_path(reader: ReaderState, obj: Obj) -> str:
    filename = required(obj, "filename", get_str)
    return resolve(obj.take("filename", ("string",)).node, filename, reader.root_dir, reader.paths)


def _load_mesh_file(path: str, node: Node):
    try:
        return read_mesh_file(path, with_uv=True, with_normals=True)
    except ValueError as exc:
        node.fail(str(exc))


def _sphere_frame(obj: Obj, to_world: np.ndarray) -> np.ndarray:
    """Mitsuba composes to_world * translate(center) * scale(radius)."""
    r3 = to_world[:3, :3]
    gram = r3.T @ r3
    if not np.allclose(gram, np.eye(3) * gram[0, 0], rtol=1e-5, atol=1e-9 * gram[0, 0]):
        obj.node.fail("to_world of a sphere must be a similarity (Mitsuba ignores other scales)")
    radius = get_float(obj, "radius", 1.0)
    if not radius > 0:
        obj.node.fail(f"radius must be positive, got {radius}")
    local = np.diag([radius, radius, radius, 1.0])
    local[:3, 3] = get_point(obj, "center", np.zeros(3))
    return to_world @ local


def _cylinder_frame(obj: Obj) -> np.ndarray:
    """Mitsuba's cylinder from p0 to p1 of `radius`: the unit cylinder
    (z in [0, 1]) scaled, turned onto p1 - p0 and moved to p0."""
    p0 = np.asarray(get_point(obj, "p0", np.zeros(3)), np.float64)
    p1 = np.asarray(get_point(obj, "p1", np.array([0.0, 0.0, 1.0])), np.float64)
    radius = get_float(obj, "radius", 1.0)
    axis = p1 - p0
    length = float(np.linalg.norm(axis))
    if not radius > 0 or length == 0:
        obj.node.fail("a cylinder needs a positive radius and p0 != p1")
    z = axis / length
    # Mitsuba's Frame3f(z) (Duff et al.'s basis): the same x, y keep the
    # angle phi, and so a texture's u, where Mitsuba has it.
    sign = 1.0 if z[2] >= 0.0 else -1.0
    a, b = -1.0 / (sign + z[2]), z[0] * z[1] * -1.0 / (sign + z[2])
    x = np.array([1.0 + sign * z[0] * z[0] * a, sign * b, -sign * z[0]])
    y = np.array([b, sign + z[1] * z[1] * a, -z[1]])
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x * radius, y * radius, axis, p0
    return m


def _circular(obj: Obj, m: np.ndarray) -> np.ndarray:
    """Mitsuba reads a cylinder's radius and length off its transform and
    only warns when that shears it or scales x and y apart, then renders a
    different cylinder than the transformed mesh: we refuse instead."""
    cols = m[:3, :3]
    gram = cols.T @ cols
    scale = float(np.max(np.diag(gram)))
    off = gram - np.diag(np.diag(gram))
    if np.max(np.abs(off)) > 1e-6 * scale or abs(gram[0, 0] - gram[1, 1]) > 1e-6 * scale:
        obj.node.fail("a cylinder's to_world must not shear it or scale its cross-section unevenly "
                      "(Mitsuba warns and renders another cylinder)")
    return m


# -- the built-in shapes in their local frames ---------------------------------------

def _orient_outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Wind every triangle of a shape centred on the origin to face outward."""
    v0 = vertices[faces[:, 0]]
    normal = np.cross(vertices[faces[:, 1]] - v0, vertices[faces[:, 2]] - v0)
    inward = np.einsum("ij,ij->i", normal, vertices[faces].mean(axis=1)) < 0
    faces = faces.copy()
    faces[inward] = faces[inward][:, ::-1]
    return faces


def _rectangle():
    """Mitsuba's rectangle: [-1, 1]^2 in z = 0, front +z."""
    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


@functools.lru_cache(maxsize=1)
def _cube():
    """Mitsuba's cube: [-1, 1]^3, 24 vertices, faces outward."""
    vertices, faces = [], []
    for axis in range(3):
        for side in (-1.0, 1.0):
            base = len(vertices)
            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis], p[(axis + 1) % 3], p[(axis + 2) % 3] = side, a, b
                vertices.append(p)
            faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    vertices = np.array(vertices)
    return vertices, _orient_outward(vertices, np.array(faces))


@functools.lru_cache(maxsize=1)
def _unit_sphere():
    """Mitsuba's sphere is analytic; 20,480 flat triangles (subdivision 5 of
    an icosahedron) keep the chord error under 0.03% of the radius."""
    import trimesh  # heavy (0.15 s): only scenes with a sphere pay it
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    vertices = np.asarray(mesh.vertices, np.float64)
    return vertices, _orient_outward(vertices, np.asarray(mesh.faces, np.int64))


@functools.lru_cache(maxsize=1)
def _disk():
    """Mitsuba's disk: the unit disk in z = 0, front +z; a fan of SEGMENTS
    triangles around its centre."""
    phi = 2 * np.pi * np.arange(SEGMENTS) / SEGMENTS
    rim = np.stack([np.cos(phi), np.sin(phi), np.zeros(SEGMENTS)], axis=1)
    vertices = np.concatenate([[[0.0, 0.0, 0.0]], rim])
    j = np.arange(SEGMENTS)
    return vertices, np.stack([np.zeros(SEGMENTS, np.int64), 1 + j, 1 + (j + 1) % SEGMENTS], axis=1)


@functools.lru_cache(maxsize=1)
def _cylinder():
    """Mitsuba's cylinder: radius 1 around z in [0, 1], open (no caps),
    front outward; SEGMENTS quads."""
    phi = 2 * np.pi * np.arange(SEGMENTS) / SEGMENTS
    ring = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    vertices = np.concatenate([np.c_[ring, np.zeros(SEGMENTS)], np.c_[ring, np.ones(SEGMENTS)]])
    j = np.arange(SEGMENTS)
    jn = (j + 1) % SEGMENTS
    faces = np.concatenate([np.stack([j, jn, SEGMENTS + jn], 1), np.stack([j, SEGMENTS + jn, SEGMENTS + j], 1)])
    return vertices, faces.astype(np.int64)


# -- their texture coordinates, as Mitsuba's (seams split) -------------------------
# The cube's (u, v) at `_cube`'s vertices, face by face (axis x, y, z; side
# -1 then +1), read off Mitsuba 3's cube by tracing rays at its corners.
_CUBE_UV = np.array([
    [0, 0], [1, 0], [1, 1], [0, 1], [0, 1], [1, 1], [1, 0], [0, 0],
    [0, 0], [1, 0], [1, 1], [0, 1], [1, 1], [1, 0], [0, 0], [0, 1],
    [1, 0], [1, 1], [0, 1], [0, 0], [0, 0], [0, 1], [1, 1], [1, 0]], np.float64)


def _rectangle_uv():
    v, f = _rectangle()
    return v, f, (v[:, :2] + 1.0) / 2.0


def _cube_uv():
    v, f = _cube()
    return v, f, _CUBE_UV.copy()


def _sphere_uv():
    """uv = (phi / 2 pi, theta / pi) about z, as Mitsuba's sphere; each
    triangle gets its own corners, so one that straddles phi = 0 can take
    u + 1 for its corners past the seam, and a corner on a pole the mean u
    of the other two."""
    v, f = _unit_sphere()
    corners = v[f]                                     # (T, 3, 3)
    u = np.arctan2(corners[..., 1], corners[..., 0]) / (2 * np.pi) % 1.0
    w = np.arccos(np.clip(corners[..., 2], -1.0, 1.0)) / np.pi
    pole = np.hypot(corners[..., 0], corners[..., 1]) < 1e-9
    u = np.where(pole, np.nan, u)
    span = np.nanmax(u, axis=1) - np.nanmin(u, axis=1)
    u = np.where((span > 0.5)[:, None] & (u < 0.5), u + 1.0, u)
    u = np.where(pole, np.nanmean(u, axis=1)[:, None], u)
    return corners.reshape(-1, 3), np.arange(f.size).reshape(-1, 3), np.stack([u, w], -1).reshape(-1, 2)


def _disk_uv():
    """uv = (r, phi / 2 pi), as Mitsuba's disk: the fan's centre repeated
    per triangle at the triangle's middle angle, and the rim's last vertex
    repeated at u = 1."""
    v, f = _disk()
    corners = v[f]
    j = np.arange(SEGMENTS)
    uv = np.zeros((SEGMENTS, 3, 2))
    uv[:, 0] = np.c_[np.zeros(SEGMENTS), (j + 0.5) / SEGMENTS]
    uv[:, 1] = np.c_[np.ones(SEGMENTS), j / SEGMENTS]
    uv[:, 2] = np.c_[np.ones(SEGMENTS), (j + 1) / SEGMENTS]
    return corners.reshape(-1, 3), np.arange(f.size).reshape(-1, 3), uv.reshape(-1, 2)


def _cylinder_uv():
    """uv = (phi / 2 pi, z), as Mitsuba's cylinder: a ring of SEGMENTS + 1
    columns, the last at u = 1 where the first lies."""
    n = SEGMENTS + 1
    phi = 2 * np.pi * np.arange(n) / SEGMENTS
    ring = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    vertices = np.concatenate([np.c_[ring, np.zeros(n)], np.c_[ring, np.ones(n)]])
    j = np.arange(SEGMENTS)
    faces = np.concatenate([np.stack([j, j + 1, n + j + 1], 1), np.stack([j, n + j + 1, n + j], 1)])
    u = np.arange(n) / SEGMENTS
    uv = np.concatenate([np.c_[u, np.zeros(n)], np.c_[u, np.ones(n)]])
    return vertices, faces.astype(np.int64), uv


_BUILT_IN = {"rectangle": _rectangle, "cube": _cube, "sphere": _unit_sphere, "disk": _disk,
             "cylinder": _cylinder}
_TEXTURED = {"rectangle": _rectangle_uv, "cube": _cube_uv, "sphere": _sphere_uv, "disk": _disk_uv,
             "cylinder": _cylinder_uv}
