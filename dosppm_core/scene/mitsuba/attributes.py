"""Mitsuba's `mesh_attribute` texture: a PLY's per-vertex or per-face
values (name "vertex_<prefix>" or "face_<prefix>", the file's properties
<prefix>_0, <prefix>_1, ...) as a BSDF's colour.

The kernels know only UV-mapped textures, so each shape reading one gets a
texture of its own, built so that the UV lookup gives exactly what
Mitsuba's attribute gives: every triangle its own corners and
- per face, one texel, nearest-filtered, the corners at its centre;
- per vertex, a 2x2 block, bilinear, the corners at three texel centres
  holding their values c0, c1, c2 and the fourth texel c1 + c2 - c0: the
  bilinear blend of such a block is affine, so within the triangle it is
  the barycentric interpolation of the three values, as Mitsuba's."""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from dosppm_core.scene import textures as tx
from dosppm_core.scene.mitsuba.objects import Obj
from dosppm_core.scene.mitsuba.state import ReaderState


def attribute_values(path: str, name: str, node) -> tuple[str, np.ndarray]:
    """("vertex" or "face", float64 (n, 3)) of attribute `name` of a PLY."""
    import trimesh
    element, _, prefix = name.partition("_")
    if element not in ("vertex", "face") or not prefix:
        node.fail(f"mesh attribute {name!r}: the name must be vertex_<name> or face_<name>")
    loaded = trimesh.load(path, process=False)
    raw = getattr(loaded, "metadata", {}).get("_ply_raw", {}).get(element)
    names = [] if raw is None else [n for n in raw["data"].dtype.names if n.startswith(prefix + "_")]
    if not names:
        node.fail(f"mesh attribute {name!r}: {path} has no {element} properties {prefix}_0, {prefix}_1, ...")
    values = np.stack([np.asarray(raw["data"][f"{prefix}_{i}"], np.float64) for i in range(len(names))], -1)
    if values.shape[1] == 1:
        values = np.repeat(values, 3, axis=1)
    if values.shape[1] != 3:
        node.fail(f"mesh attribute {name!r}: {values.shape[1]} channels (only 1 or 3)")
    return element, values


def per_triangle(element: str, values: np.ndarray, vertices, faces):
    """(unshared vertices, faces, uv, Texture) of the mesh carrying the
    attribute as a UV texture (the module docstring's layout)."""
    t = len(faces)
    side = max(1, math.ceil(math.sqrt(t)))
    k = np.arange(t)
    bx, by = k % side, k // side
    corners = np.asarray(vertices)[faces].reshape(-1, 3)
    new_faces = np.arange(3 * t).reshape(-1, 3)
    if element == "face":
        texels = np.zeros((math.ceil(t / side), side, 3))
        texels[by, bx] = values[:t]
        h, w = texels.shape[:2]
        uv = np.repeat(np.c_[(bx + 0.5) / w, (by + 0.5) / h], 3, axis=0)
        return corners, new_faces, uv, tx.bitmap("face attribute", texels, "nearest", "clamp")
    c = values[faces]                                        # (T, 3 corners, 3)
    texels = np.zeros((2 * math.ceil(t / side), 2 * side, 3))
    texels[2 * by, 2 * bx], texels[2 * by, 2 * bx + 1], texels[2 * by + 1, 2 * bx] = c[:, 0], c[:, 1], c[:, 2]
    texels[2 * by + 1, 2 * bx + 1] = c[:, 1] + c[:, 2] - c[:, 0]
    h, w = texels.shape[:2]
    uv = np.stack([np.c_[(2 * bx + 0.5) / w, (2 * by + 0.5) / h], np.c_[(2 * bx + 1.5) / w, (2 * by + 0.5) / h],
                   np.c_[(2 * bx + 0.5) / w, (2 * by + 1.5) / h]], 1).reshape(-1, 2)
    return corners, new_faces, uv, tx.bitmap("vertex attribute", texels, "bilinear", "clamp")


def shape_attribute(reader: ReaderState, material: int, obj: Obj, path: str | None, vertices, faces):
    """(vertices, faces, uv, material) of a shape whose material reads a
    mesh attribute (as its colour, a mask's opacity or a blend's weight):
    its own texture and material; None for other shapes."""
    builder = reader.builder
    base = builder._materials[material]
    fields = [f for f in ("texture", "opacity_texture", "blend_texture")
              if getattr(base, f) in reader.attribute_ids]
    if not fields:
        return None
    if len(fields) > 1:
        obj.node.fail("more than one mesh attribute read by one material is unsupported")
    name, node = reader.attribute_ids[getattr(base, fields[0])]
    if path is None or not path.lower().endswith(".ply"):
        obj.node.fail(f"mesh attribute {name!r}: only a PLY shape carries attributes here")
    element, values = attribute_values(path, name, node)
    expected = len(vertices) if element == "vertex" else len(faces)
    if len(values) != expected:
        node.fail(f"mesh attribute {name!r}: {len(values)} values for {expected} {element}s")
    vertices, faces, uv, tex = per_triangle(element, values, vertices, faces)
    own = dataclasses.replace(base, name=f"{base.name}@{obj.node.line}:{len(builder._materials)}",
                              **{fields[0]: builder.add_texture(tex)})
    return vertices, faces, uv, builder.add_material(own, obj.where())
