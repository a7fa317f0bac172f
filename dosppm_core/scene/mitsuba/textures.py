"""Texture plugins: bitmap (filename, filter_type, wrap_mode, raw, to_uv,
format), checkerboard (color0, color1, to_uv), rawconstant (value: one
float or a vector, no colour conversion: a one-texel texture) and
mesh_attribute (name; see `attributes`), nested in a BSDF under a
parameter's name or referenced by id (`<ref name="reflectance" id="tex"/>`).

One <texture> object is one texture of the scene however often it is
referenced. A BSDF reads its colour parameters through `TextureParams`,
which returns either a constant RGB or a texture id, and fails on a
texture nested under a name the BSDF does not read."""
from __future__ import annotations

import os

import numpy as np

from dosppm_core.scene import textures as tx
from dosppm_core.scene.mitsuba.objects import Obj, Ref
from dosppm_core.scene.mitsuba.params import (finish, get_bool, get_float, get_matrix, get_rgb, get_str,
                                              required)
from dosppm_core.scene.mitsuba.state import ReaderState
from dosppm_core.scene.mitsuba.xmltree import resolve


def read_texture(reader: ReaderState, obj: Obj) -> int:
    """The builder's id of the texture `obj` describes (read once)."""
    if id(obj) not in reader.textures:
        reader.children(obj, ())          # no textures of textures
        if obj.type == "mesh_attribute":
            # A one-texel stand-in: each PLY shape reading it gets a texture
            # of its own (`attributes.shape_attribute`).
            name = required(obj, "name", get_str)
            texture = tx.bitmap(obj.name(), np.zeros((1, 1, 3)))
        elif obj.type == "rawconstant":
            texture = _rawconstant(obj)
        else:
            texture = _bitmap(reader, obj) if obj.type == "bitmap" else _checkerboard(obj)
        finish(obj)
        reader.textures[id(obj)] = reader.builder.add_texture(texture)
        if obj.type == "mesh_attribute":
            reader.attribute_ids[reader.textures[id(obj)]] = (name, obj.node)
    return reader.textures[id(obj)]


def light_texture(reader: ReaderState, obj: Obj, name: str) -> tx.Texture | None:
    """The texture an emitter gives under parameter `name` (nested or by
    reference), read apart from the materials' table (`LightTable` keeps its
    own); None if it gives none. Any other nested object is refused."""
    found = None
    for child, target in zip(obj.children, reader.children(obj, ("texture",))):
        if child.node.attrib.get("name") != name or found is not None:
            child.node.fail(f"{obj.node.label} takes one texture, named {name!r}")
        if target.type not in ("bitmap", "checkerboard"):
            child.node.fail(f"a {target.type} texture is unsupported on an emitter")
        if name in obj.props:
            child.node.fail(f"parameter {name!r} given twice (a value and a texture)")
        found = target
    if found is None:
        return None
    reader.children(found, ())
    texture = _bitmap(reader, found) if found.type == "bitmap" else _checkerboard(found)
    finish(found)
    return texture


def _uv_map(obj: Obj) -> tuple:
    """Mitsuba's to_uv: the 2D affine part (rows and columns x, y and the
    translation) of the 4x4 transform given."""
    m = get_matrix(obj, "to_uv")
    return (m[0, 0], m[0, 1], m[0, 3], m[1, 0], m[1, 1], m[1, 3])


def _bitmap(reader: ReaderState, obj: Obj) -> tx.Texture:
    filename = required(obj, "filename", get_str)
    node = obj.take("filename", ("string",)).node
    path = resolve(node, filename, reader.root_dir, reader.paths)
    raw = get_bool(obj, "raw", False)
    filter_type = get_str(obj, "filter_type", "bilinear")
    wrap_mode = get_str(obj, "wrap_mode", "repeat")
    get_bool(obj, "accel")                # a GPU lookup strategy: the same values
    fmt = obj.take("format", ("string",))   # storage precision: we keep float32 texels
    if fmt is not None and fmt.value not in ("auto", "variant", "float16", "fp16", "uint8"):
        fmt.node.fail(f"format {fmt.value!r} is unknown (auto, variant, float16 or uint8)")
    for name, value, allowed in (("filter_type", filter_type, tx.FILTERS),
                                 ("wrap_mode", wrap_mode, tx.WRAP_MODES)):
        if value not in allowed:
            obj.take(name, ("string",)).node.fail(
                f"{name} {value!r} is unsupported (known: {', '.join(allowed)})")
    key = (os.path.realpath(path), raw)
    if key not in reader.images:     # one file, one texel block, however many textures read it
        try:
            reader.images[key] = tx.read_image(path, raw=raw)
        except ValueError as exc:
            node.fail(str(exc))
    texels = reader.images[key]
    return tx.bitmap(obj.name(), texels, filter_type, wrap_mode, _uv_map(obj))


def _rawconstant(obj: Obj) -> tx.Texture:
    """Mitsuba's rawconstant: its value as it is (one float is repeated)."""
    prop = required(obj, "value", lambda o, n: o.take(n, ("float", "integer", "vector", "point")))
    value = prop.value if prop.kind in ("vector", "point") else (float(prop.value),) * 3
    return tx.bitmap(obj.name(), np.array(value, np.float64).reshape(1, 1, 3), "nearest")


def _checkerboard(obj: Obj) -> tx.Texture:
    # Mitsuba's defaults: color0 0.4, color1 0.2.
    return tx.checkerboard(obj.name(), get_rgb(obj, "color0", 0.4), get_rgb(obj, "color1", 0.2),
                           _uv_map(obj))


class TextureParams:
    """A BSDF's nested or referenced textures, by parameter name."""

    def __init__(self, reader: ReaderState, obj: Obj, skip=()):
        """`skip`: tags of children the BSDF reads itself (a mask's nested <bsdf>)."""
        self.reader, self.obj = reader, obj
        self.named: dict = {}
        for child in obj.children:
            target = child
            if isinstance(child, Ref):
                target = reader.ids.get(child.id) or child.node.fail(f"unknown id {child.id!r}")
            if target.tag in skip:
                continue
            if target.tag != "texture":
                child.node.fail(f"not allowed inside {obj.node.label}")
            name = child.node.attrib.get("name")
            if not name:
                child.node.fail("a texture inside a BSDF needs the name of the parameter it gives")
            if name in self.named:
                child.node.fail(f"parameter {name!r} given twice")
            self.named[name] = [child, target, False]

    def rgb(self, name: str, default: float) -> tuple:
        """(RGB, -1) of a constant parameter, or (None, texture id) of a
        textured one."""
        if name not in self.named:
            return get_rgb(self.obj, name, default), -1
        return None, self._texture(name)

    def scalar(self, name: str, default) -> tuple:
        """(number, -1) of a constant parameter (`default` when absent), or
        (None, texture id) of a textured one (the kernels take its
        luminance, as Mitsuba's eval_1 of an RGB texture)."""
        if name not in self.named:
            return get_float(self.obj, name, default), -1
        return None, self._texture(name)

    def _texture(self, name: str) -> int:
        entry = self.named[name]
        if name in self.obj.props:
            entry[0].node.fail(f"parameter {name!r} given twice (a value and a texture)")
        entry[2] = True
        return read_texture(self.reader, entry[1])

    def same(self, a: str, b: str, default: float) -> tuple:
        """(RGB, texture id) of two parameters that must agree (a glass's
        one tint): equal constants or the same texture object."""
        rgb_a, tex_a = self.rgb(a, default)
        rgb_b, tex_b = self.rgb(b, default)
        if tex_a != tex_b or (tex_a < 0 and not np.allclose(rgb_a, rgb_b)):
            self.obj.node.fail(f"{a} and {b} differ; our glass has one tint")
        return rgb_a, tex_a

    def finish(self) -> None:
        for name, (child, _target, used) in self.named.items():
            if not used:
                child.node.fail(f"a texture for {name!r} is unsupported here (only constant values)")
