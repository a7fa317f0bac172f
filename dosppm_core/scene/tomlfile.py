"""The project's own scene format: one TOML file, documented with a full
example in `docs/scene-format.md`.

Tables: `[camera]`, `[materials.NAME]`, `[[shapes]]`, `[[lights]]` and an
optional `[render]`. Every key is checked: an unknown key, a key that the
entry's type does not use, a wrong type or a bad value is a `SceneError`
whose one-line message names the file and the key path, e.g.
`scene.toml: shapes[2].colour: unknown key (known: type, material, ...)`.
Entries of `[[shapes]]` and `[[lights]]` are counted from 0 in messages.
"""
from __future__ import annotations

import math
import os
import tomllib

import numpy as np

from dosppm_core.scene import envmap, shapes
from dosppm_core.scene.model import Camera, Material, Scene, SceneBuilder, SceneError

_TOP_KEYS = ("camera", "materials", "shapes", "lights", "render")
_CAMERA_KEYS = ("position", "look_at", "up", "fov", "fov_axis", "width", "height",
                "aperture_radius", "focus_distance", "pixel_filter", "filter_radius", "filter_stddev")
# Keys each material type reads; anything else would be silently ignored,
# so it is an error instead.
_MATERIAL_KEYS = {
    "diffuse": ("type", "reflectance", "emission", "two_sided", "opacity"),
    "mirror": ("type", "reflectance", "emission", "two_sided", "opacity"),
    "glossy": ("type", "reflectance", "roughness", "emission", "two_sided", "opacity"),
    "glass": ("type", "reflectance", "ior", "emission", "opacity"),
    "roughdielectric": ("type", "reflectance", "specular", "ior", "roughness", "distribution",
                        "emission", "opacity"),
    "plastic": ("type", "reflectance", "specular", "ior", "nonlinear", "emission", "two_sided", "opacity"),
    "roughplastic": ("type", "reflectance", "specular", "ior", "roughness", "distribution", "nonlinear",
                     "emission", "two_sided", "opacity"),
}
_TRANSFORM_KEYS = ("translate", "rotate", "scale", "matrix")
_SHAPE_KEYS = {
    "mesh": ("type", "file", "material") + _TRANSFORM_KEYS,
    "rectangle": ("type", "material") + _TRANSFORM_KEYS,
    "box": ("type", "material") + _TRANSFORM_KEYS,
    "sphere": ("type", "material") + _TRANSFORM_KEYS,
}
_PRIMITIVES = {
    "rectangle": shapes.rectangle,
    "box": shapes.box,
    # Fixed tessellation: 20,480 triangles, flat faces within 0.03% of the
    # unit sphere -- smooth enough for glass, cheap enough for many spheres.
    "sphere": lambda: shapes.ico_sphere(5),
}
_LIGHT_KEYS = {
    "point": ("type", "position", "intensity"),
    "spot": ("type", "position", "target", "intensity", "cutoff_angle", "beam_width"),
    "directional": ("type", "direction", "irradiance"),
    "environment": ("type", "radiance", "file", "scale", "rotate"),
}
_REQUIRED = object()


def load_toml(path: str | os.PathLike) -> Scene:
    """Read a TOML scene file into a validated `Scene`. Mesh files are
    found relative to the TOML file. `scene.render_settings` holds the
    `[render]` table as a plain dict (empty when absent)."""
    path = os.fspath(path)
    return scene_from_document(_read_document(path), path, os.path.splitext(os.path.basename(path))[0],
                               os.path.dirname(os.path.abspath(path)))


def scene_from_document(doc: dict, path: str, name: str, base_dir: str) -> Scene:
    """A `Scene` from the tables of a scene file, already parsed (a dict
    of the same shape: the Python API's `load`). `path` names the source
    in error messages; mesh files are found relative to `base_dir`."""
    if not isinstance(doc, dict):
        raise SceneError(f"{path}: a scene is a table (dict) of camera, materials, shapes and lights")
    _check_keys(doc, _TOP_KEYS, path, "")
    builder = SceneBuilder(source=path, name=name)
    builder.camera = _read_camera(doc, path)
    materials = _read_materials(doc, builder, path)
    used = {_read_shape(shape, builder, path, f"shapes[{i}]", base_dir)
            for i, shape in enumerate(_entries(doc, "shapes", path))}
    lights = _entries(doc, "lights", path)
    for i, light in enumerate(lights):
        _read_light(light, builder, path, f"lights[{i}]", base_dir)
    if not lights and not any(max(materials[name].emission) > 0 for name in used):
        raise SceneError(f"{path}: lights: the scene has no light; add a [[lights]] entry "
                         f"or give a shape a material with an emission")
    render = _read_render(doc, path)
    scene = builder.build()
    scene.render_settings = render
    return scene


def _read_document(path: str) -> dict:
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise SceneError(f"{path}: no such scene file") from None
    except OSError as e:
        raise SceneError(f"{path}: cannot read: {e.strerror}") from None
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{path}: invalid TOML: {e}") from None


# -- checked access to values ------------------------------------------------

def _key(table_path: str, key: str) -> str:
    return f"{table_path}.{key}" if table_path else key


def _check_keys(table: dict, allowed, path: str, table_path: str) -> None:
    for key in table:
        if key not in allowed:
            raise SceneError(f"{path}: {_key(table_path, key)}: unknown key "
                             f"(known: {', '.join(allowed)})")


def _kind_of(table: dict, keys_by_type: dict, what: str, path: str, where: str) -> str:
    """The `type` of a `what` (material, shape, light) entry, one of
    `keys_by_type`'s, its keys checked like `_check_keys`, except that a key
    another type of `what` reads is reported as unused by this type rather
    than as unknown."""
    kind = _string(table, "type", path, where)
    if kind not in keys_by_type:
        raise SceneError(f"{path}: {where}.type: unknown {what} type {kind!r} "
                         f"(known: {', '.join(keys_by_type)})")
    allowed = keys_by_type[kind]
    for key in table:
        if key not in allowed and any(key in keys for keys in keys_by_type.values()):
            raise SceneError(f"{path}: {where}.{key}: not used by a {kind!r} {what} "
                             f"(its keys: {', '.join(allowed)})")
    _check_keys(table, allowed, path, where)
    return kind


def _table(value, path: str, where: str) -> dict:
    if not isinstance(value, dict):
        raise SceneError(f"{path}: {where}: expected a table, got {type(value).__name__}")
    return value


def _entries(doc: dict, name: str, path: str) -> list:
    """The `[[name]]` array of tables (empty when absent)."""
    value = doc.get(name, [])
    if not isinstance(value, list):
        raise SceneError(f"{path}: {name}: expected [[{name}]] entries (an array of tables)")
    return [_table(v, path, f"{name}[{i}]") for i, v in enumerate(value)]


def _get(table: dict, key: str, path: str, where: str, default=_REQUIRED):
    if key in table:
        return table[key]
    if default is _REQUIRED:
        raise SceneError(f"{path}: {_key(where, key)}: missing")
    return default


def _number(table: dict, key: str, path: str, where: str, default=_REQUIRED) -> float:
    value = _get(table, key, path, where, default)
    # bool is an int in Python but `true` is no number in TOML.
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SceneError(f"{path}: {_key(where, key)}: expected a finite number, got {value!r}")
    return float(value)


def _integer(table: dict, key: str, path: str, where: str) -> int:
    value = _get(table, key, path, where)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise SceneError(f"{path}: {_key(where, key)}: expected a positive integer, got {value!r}")
    return value


def _string(table: dict, key: str, path: str, where: str, default=_REQUIRED) -> str:
    value = _get(table, key, path, where, default)
    if not isinstance(value, str):
        raise SceneError(f"{path}: {_key(where, key)}: expected a string, got {value!r}")
    return value


def _boolean(table: dict, key: str, path: str, where: str, default: bool) -> bool:
    value = _get(table, key, path, where, default)
    if not isinstance(value, bool):
        raise SceneError(f"{path}: {_key(where, key)}: expected true or false, got {value!r}")
    return value


def _numbers(value, n: int, path: str, where: str) -> np.ndarray:
    """A list of exactly `n` finite numbers."""
    ok = isinstance(value, list) and len(value) == n and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in value)
    if not ok:
        raise SceneError(f"{path}: {where}: expected a list of {n} finite numbers, got {value!r}")
    return np.array(value, np.float64)


def _vec3(table: dict, key: str, path: str, where: str, default=_REQUIRED) -> tuple:
    value = _get(table, key, path, where, default)
    return tuple(_numbers(value, 3, path, _key(where, key)).tolist())


def _rgb(table: dict, key: str, path: str, where: str, default) -> tuple:
    """An RGB triple, or one number meaning grey."""
    value = _get(table, key, path, where, default)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value] * 3
    return tuple(_numbers(value, 3, path, _key(where, key)).tolist())


# -- tables ------------------------------------------------------------------

def _read_camera(doc: dict, path: str) -> Camera:
    if "camera" not in doc:
        raise SceneError(f"{path}: camera: missing [camera] table")
    cam = _table(doc["camera"], path, "camera")
    _check_keys(cam, _CAMERA_KEYS, path, "camera")
    for key in ("width", "height"):
        if key not in cam:
            raise SceneError(f"{path}: camera.{key}: missing; the camera needs a resolution "
                             f"(width and height in pixels)")
    position = _vec3(cam, "position", path, "camera")
    look_at = _vec3(cam, "look_at", path, "camera")
    # Focus on the look-at point unless told otherwise (only a lens uses it).
    focus = float(np.linalg.norm(np.subtract(look_at, position))) or 1.0
    return Camera(
        position=position, look_at=look_at,
        up=_vec3(cam, "up", path, "camera", [0.0, 1.0, 0.0]),
        fov_deg=_number(cam, "fov", path, "camera"),
        width=_integer(cam, "width", path, "camera"),
        height=_integer(cam, "height", path, "camera"),
        fov_axis=_string(cam, "fov_axis", path, "camera", "x"),
        aperture_radius=_number(cam, "aperture_radius", path, "camera", 0.0),
        focus_distance=_number(cam, "focus_distance", path, "camera", focus),
        pixel_filter=_string(cam, "pixel_filter", path, "camera", "box"),
        filter_radius=_number(cam, "filter_radius", path, "camera", None) if "filter_radius" in cam else None,
        filter_stddev=_number(cam, "filter_stddev", path, "camera", 0.5))


def _read_materials(doc: dict, builder: SceneBuilder, path: str) -> dict:
    """Add every `[materials.NAME]`; returns them by name."""
    materials = {}
    for name, mat in _table(doc.get("materials", {}), path, "materials").items():
        where = f"materials.{name}"
        mat = _table(mat, path, where)
        kind = _kind_of(mat, _MATERIAL_KEYS, "material", path, where)
        material = Material(
            name, kind,
            reflectance=_rgb(mat, "reflectance", path, where,
                             [0.5, 0.5, 0.5] if kind in ("diffuse", "plastic", "roughplastic") else 1.0),
            ior=_number(mat, "ior", path, where, 1.5),
            roughness=_number(mat, "roughness", path, where, 0.1),
            emission=_rgb(mat, "emission", path, where, 0.0),
            two_sided=_boolean(mat, "two_sided", path, where, True),
            specular=_rgb(mat, "specular", path, where, 1.0),
            distribution=_string(mat, "distribution", path, where, "ggx"),
            nonlinear=_boolean(mat, "nonlinear", path, where, False),
            opacity=_number(mat, "opacity", path, where, 1.0))
        builder.add_material(material, where=f"{path}: {where}")
        materials[name] = material
    return materials


def _read_shape(shape: dict, builder: SceneBuilder, path: str, where: str, base_dir: str) -> str:
    """Add one `[[shapes]]` entry; returns its material's name."""
    kind = _kind_of(shape, _SHAPE_KEYS, "shape", path, where)
    material = builder.material_id(_string(shape, "material", path, where),
                                   f"{path}: {where}.material")
    transform = _read_transform(shape, path, where)
    if kind == "mesh":
        file = _string(shape, "file", path, where)
        vertices, faces, uv = load_mesh_file(os.path.join(base_dir, file), path, f"{where}.file")
        mesh_where = f"{path}: {where}.file ({file})"
    else:
        vertices, faces = _PRIMITIVES[kind]()
        uv = None
        mesh_where = f"{path}: {where}"
    if transform is not None and np.linalg.det(transform[:3, :3]) < 0:
        # A mirroring transform turns counter-clockwise into clockwise;
        # reverse the winding so the front (emitting) side stays the front,
        # as pbrt does for transforms that swap handedness.
        faces = faces[:, ::-1]
    builder.add_mesh(vertices, faces, material, mesh_where, transform, uv=uv)
    return shape["material"]


def load_mesh_file(full: str, path: str, where: str):
    """(vertices, triangles, uv or None) of any mesh file trimesh reads;
    errors name the scene file `path` and the element `where`."""
    if not os.path.isfile(full):
        raise SceneError(f"{path}: {where}: no such file {full!r}")
    try:
        return read_mesh_file(full, with_uv=True)
    except ValueError as e:
        raise SceneError(f"{path}: {where}: {e}") from None


def read_mesh_file(full: str, with_uv: bool = False, with_normals: bool = False):
    """(vertices float64, triangles int64) of any mesh file trimesh reads,
    or ValueError with a one-line reason. Shared by every scene loader.
    `with_uv` adds the vertices' texture coordinates (float64 (nv, 2), or
    None if the file has none) in Mitsuba's convention: an OBJ's v is
    turned into 1 - v, as Mitsuba's OBJ reader does (v = 0 is then the
    image's top row); a PLY's are taken as stored. `with_normals` adds
    the file's vertex normals (float64 (nv, 3), or None if it has none)."""
    import trimesh  # imported here: half a second that scenes without meshes never pay
    try:
        # Only geometry is used: skipping materials also keeps trimesh from
        # importing Pillow for the textures an OBJ's .mtl may name.
        loaded = trimesh.load(full, process=False, skip_materials=True)
        vertices, faces, uv, normals = _flatten(loaded)
    # trimesh's readers raise many exception types on bad input (ValueError,
    # KeyError, IndexError, struct.error...): all mean "cannot read".
    except Exception as e:  # noqa: BLE001
        detail = (str(e).splitlines() or [type(e).__name__])[0]
        raise ValueError(f"cannot read mesh {full!r}: {detail}") from None
    if len(faces) == 0:
        raise ValueError(f"mesh {full!r} has no triangles")
    if not with_uv:
        return vertices, faces
    if uv is not None and full.lower().endswith(".obj"):
        uv[:, 1] = 1.0 - uv[:, 1]
    return (vertices, faces, uv, normals) if with_normals else (vertices, faces, uv)


def _flatten(loaded):
    """One triangle soup (vertices, faces, uv or None) from a trimesh
    Trimesh or Scene, with each node's transform applied. Done here rather
    than with force="mesh", whose Scene.dump deep-copies every visual and
    so needs Pillow. Parts without UVs get (0, 0) beside parts with them;
    the file's vertex normals likewise (zero where a part has none)."""
    if hasattr(loaded, "graph"):
        parts = []
        for node in loaded.graph.nodes_geometry:
            transform, name = loaded.graph[node]
            parts.append((loaded.geometry[name], transform))
    else:
        parts = [(loaded, None)]
    vertices, faces, uvs, normals, offset = [], [], [], [], 0
    for mesh, transform in parts:
        f = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64)
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            continue                      # point clouds, paths: no triangles
        v = np.asarray(mesh.vertices, np.float64)
        if transform is not None and not np.array_equal(transform, np.eye(4)):
            v = v @ transform[:3, :3].T + transform[:3, 3]
        vertices.append(v)
        faces.append(f + offset)
        uvs.append(_mesh_uv(mesh, len(v)))
        normals.append(_mesh_normals(mesh, len(v), transform))
        offset += len(v)
    if not faces:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), None, None
    uv = nrm = None
    if any(u is not None for u in uvs):
        uv = np.concatenate([np.zeros((len(v), 2)) if u is None else u for v, u in zip(vertices, uvs)])
    if any(n is not None for n in normals):
        nrm = np.concatenate([np.zeros((len(v), 3)) if n is None else n for v, n in zip(vertices, normals)])
    return np.concatenate(vertices), np.concatenate(faces), uv, nrm


def _mesh_normals(mesh, count: int, transform):
    """The vertex normals a mesh file gave (OBJ vn, PLY nx ny nz), float64,
    moved by a node's `transform`; None without. trimesh keeps a file's in
    its cache and would compute its own (not Mitsuba's) on `vertex_normals`."""
    cache = getattr(mesh, "_cache", None)
    if cache is None or "vertex_normals" not in cache:
        return None
    n = np.array(cache["vertex_normals"], np.float64)
    if n.shape != (count, 3):
        return None
    if transform is not None and not np.array_equal(transform, np.eye(4)):
        n = n @ np.linalg.inv(np.asarray(transform, np.float64)[:3, :3])
    return n


def _mesh_uv(mesh, count: int):
    """A trimesh mesh's per-vertex UVs (float64 copy), None without."""
    uv = getattr(getattr(mesh, "visual", None), "uv", None)
    if uv is None:
        return None
    uv = np.array(uv, np.float64)
    return uv if uv.shape == (count, 2) else None


def _read_transform(shape: dict, path: str, where: str) -> np.ndarray | None:
    """The object-to-world 4x4 matrix: `matrix` as given, or
    translate * rotate * scale (scale applied first, then the rotations in
    the order listed, then the translation). None when there is none."""
    if "matrix" in shape:
        others = [k for k in ("translate", "rotate", "scale") if k in shape]
        if others:
            raise SceneError(f"{path}: {where}.matrix: cannot be combined with {', '.join(others)}")
        return _read_matrix(shape["matrix"], path, f"{where}.matrix")
    if not any(k in shape for k in _TRANSFORM_KEYS):
        return None
    linear = np.diag(_read_scale(shape, path, where))
    for rotation in _read_rotations(shape, path, where):
        linear = rotation @ linear
    m = np.eye(4)
    m[:3, :3] = linear
    m[:3, 3] = _vec3(shape, "translate", path, where, [0.0, 0.0, 0.0])
    return m


def _read_matrix(value, path: str, where: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != 4:
        raise SceneError(f"{path}: {where}: expected 4 rows of 4 numbers, got {value!r}")
    m = np.stack([_numbers(row, 4, path, f"{where}[{i}]") for i, row in enumerate(value)])
    if not np.array_equal(m[3], [0.0, 0.0, 0.0, 1.0]):
        raise SceneError(f"{path}: {where}: last row must be [0, 0, 0, 1] (no projection)")
    if np.linalg.matrix_rank(m[:3, :3]) < 3:
        raise SceneError(f"{path}: {where}: matrix is singular")
    return m


def _read_scale(shape: dict, path: str, where: str) -> np.ndarray:
    scale = _rgb(shape, "scale", path, where, 1.0)
    if 0.0 in scale:
        raise SceneError(f"{path}: {where}.scale: must not be zero, got {list(scale)}")
    return np.array(scale)


def _read_rotations(shape: dict, path: str, where: str) -> list[np.ndarray]:
    """`rotate` = [x, y, z, degrees] or a list of such, as 3x3 matrices."""
    value = shape.get("rotate", [])
    if not isinstance(value, list):
        raise SceneError(f"{path}: {where}.rotate: expected [x, y, z, degrees] or a list of such, "
                         f"got {value!r}")
    nested = bool(value) and isinstance(value[0], list)
    listed = value if nested else ([value] if value else [])
    rotations = []
    for i, item in enumerate(listed):
        item_where = f"{where}.rotate" + (f"[{i}]" if nested else "")
        ax, ay, az, degrees = _numbers(item, 4, path, item_where)
        if ax == ay == az == 0:
            raise SceneError(f"{path}: {item_where}: rotation axis is zero")
        rotations.append(shapes.rotation_matrix((ax, ay, az), degrees))
    return rotations


def _read_light(light: dict, builder: SceneBuilder, path: str, where: str, base_dir: str) -> None:
    kind = _kind_of(light, _LIGHT_KEYS, "light", path, where)
    if kind == "directional":
        builder.add_directional_light(_vec3(light, "direction", path, where),
                                      _rgb(light, "irradiance", path, where, _REQUIRED), f"{path}: {where}")
        return
    if kind == "environment":
        _read_environment(light, builder, path, where, base_dir)
        return
    position = _vec3(light, "position", path, where)
    intensity = _rgb(light, "intensity", path, where, _REQUIRED)
    if kind == "point":
        builder.add_point_light(position, intensity, f"{path}: {where}")
        return
    # Mitsuba's defaults: a 20 degree cutoff, full intensity to 3/4 of it.
    beam = _number(light, "beam_width", path, where) if "beam_width" in light else None
    builder.add_spot_light(position, _vec3(light, "target", path, where), intensity,
                           _number(light, "cutoff_angle", path, where, 20.0), beam, f"{path}: {where}")


def _read_environment(light: dict, builder: SceneBuilder, path: str, where: str, base_dir: str) -> None:
    """A uniform `radiance`, or a lat-long OpenEXR `file` (Mitsuba's
    envmap layout) times `scale`, turned by `rotate`."""
    scale = _number(light, "scale", path, where, 1.0)
    rotation = np.eye(3)
    for r in _read_rotations(light, path, where):
        rotation = r @ rotation
    if "file" in light and "radiance" in light:
        raise SceneError(f"{path}: {where}: give file or radiance, not both")
    if "file" not in light:
        texels = envmap.constant_texels(np.multiply(_rgb(light, "radiance", path, where, 1.0), scale))
    else:
        file = os.path.join(base_dir, _string(light, "file", path, where))
        try:
            texels = envmap.texels_from_image(envmap.load_image(file), scale)
        except ValueError as e:
            raise SceneError(f"{path}: {where}.file: {e}") from None
    builder.set_environment(texels, rotation, f"{path}: {where}")


def _read_render(doc: dict, path: str) -> dict:
    """`[render]`: plain settings, checked only for kind here; the renderer's
    settings module owns their names and ranges."""
    render = _table(doc.get("render", {}), path, "render")
    for key, value in render.items():
        plain = isinstance(value, (str, bool, int)) or (isinstance(value, float) and math.isfinite(value))
        if not plain:
            raise SceneError(f"{path}: render.{key}: expected a number, string or boolean, got {value!r}")
    return dict(render)
