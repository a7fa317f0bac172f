"""Emitters: `area` (its radiance, constant or a bitmap or checkerboard,
becomes the emission of the material of the shape holding or referencing
it), `point`, `spot` (optionally with a
bitmap or checkerboard `texture`), `projector` (a constant or textured
`irradiance`; `scene.light_textures`), and the infinitely distant ones:
`directional`, `constant` and `envmap` (`scene.envmap`)."""
from __future__ import annotations

import math

import numpy as np

from dosppm_core.scene.mitsuba.objects import Obj
from dosppm_core.scene import envmap
from dosppm_core.scene.mitsuba.params import finish, get_float, get_matrix, get_point, get_rgb, get_str, required
from dosppm_core.scene.mitsuba.sensors import field_of_view
from dosppm_core.scene.mitsuba.state import ReaderState
from dosppm_core.scene.mitsuba.textures import light_texture
from dosppm_core.scene.mitsuba.xmltree import resolve


def area_radiance(reader: ReaderState, emitter: Obj) -> tuple:
    """(RGB radiance, emission texture id or -1) of an area emitter
    attached to a shape; a textured one's RGB is the texture's mean
    (`SceneBuilder.add_emission_texture`)."""
    if emitter.type != "area":
        emitter.node.fail("only area emitters can be attached to a shape")
    if id(emitter) not in reader.radiance:
        texture = light_texture(reader, emitter, "radiance")
        if texture is None:
            reader.radiance[id(emitter)] = (get_rgb(emitter, "radiance", 1.0), -1)
        else:
            tid, mean = reader.builder.add_emission_texture(texture)
            reader.radiance[id(emitter)] = (tuple(mean), tid)
        finish(emitter)
    return reader.radiance[id(emitter)]


def read_emitter(reader: ReaderState, obj: Obj) -> None:
    """An emitter at scene level."""
    if obj.type == "area":                # a definition: some shape must reference it
        reader.loose_area_emitters.append(obj)
        return
    if obj.type not in ("spot", "projector"):
        reader.children(obj, ())
    if obj.type in INFINITE:
        INFINITE[obj.type](reader, obj)
        return
    intensity = get_rgb(obj, "intensity", 1.0)
    if obj.type == "point":
        position = get_point(obj, "position")
        to_world = obj.take("to_world", ("transform",))
        if position is not None and to_world is not None:
            obj.node.fail("give position or to_world, not both")
        if position is None:
            position = np.eye(4)[:3, 3] if to_world is None else to_world.value[:3, 3]
        finish(obj)
        reader.builder.add_point_light(position, intensity, obj.where())
        return
    m = get_matrix(obj)
    cutoff, beam = get_float(obj, "cutoff_angle", 20.0), get_float(obj, "beam_width")
    texture = light_texture(reader, obj, "texture")
    finish(obj)
    target = m[:3, 3] + m[:3, :3] @ np.array([0.0, 0.0, 1.0])
    reader.builder.add_spot_light(m[:3, 3], target, intensity, cutoff, beam, obj.where(),
                                  m[:3, :3] @ np.array([1.0, 0.0, 0.0]), texture)


def _directional(reader: ReaderState, obj: Obj) -> None:
    """Mitsuba's directional: `direction`, or to_world's +z, and irradiance."""
    irradiance = get_rgb(obj, "irradiance", 1.0)
    direction = get_point(obj, "direction")
    to_world = obj.take("to_world", ("transform",))
    if direction is not None and to_world is not None:
        obj.node.fail("give direction or to_world, not both")
    if direction is None:
        m = np.eye(4) if to_world is None else to_world.value
        direction = m[:3, :3] @ np.array([0.0, 0.0, 1.0])
    finish(obj)
    reader.builder.add_directional_light(direction, irradiance, obj.where())


def _constant(reader: ReaderState, obj: Obj) -> None:
    """Mitsuba's constant: one radiance from every direction."""
    radiance = get_rgb(obj, "radiance", 1.0)
    finish(obj)
    reader.builder.set_environment(envmap.constant_texels(radiance), np.eye(3), obj.where())


def _envmap(reader: ReaderState, obj: Obj) -> None:
    """Mitsuba's envmap: a lat-long EXR (filename), scale, to_world (a rotation)."""
    filename = required(obj, "filename", get_str)
    path = resolve(obj.take("filename", ("string",)).node, filename, reader.root_dir, reader.paths)
    scale = get_float(obj, "scale", 1.0)
    rotation = get_matrix(obj)[:3, :3]
    finish(obj)
    try:
        texels = envmap.texels_from_image(envmap.load_image(path), scale)
    except ValueError as e:
        obj.node.fail(str(e))
    reader.builder.set_environment(texels, rotation, obj.where())


def _projector(reader: ReaderState, obj: Obj) -> None:
    """Mitsuba's projector: a constant irradiance (a square image) or an
    image; the fov is the x one its aspect gives (Mitsuba's parse_fov)."""
    texture = light_texture(reader, obj, "irradiance")
    scale = get_float(obj, "scale", 1.0)
    irradiance = np.multiply(get_rgb(obj, "irradiance", 1.0) if texture is None else 1.0, scale)
    height, width = (1, 1) if texture is None else texture.texels.shape[:2]
    fov, axis = field_of_view(obj, width, height)
    tan_x = math.tan(math.radians(fov) / 2)
    if axis == "y" or (axis == "smaller" and height < width) or (axis == "larger" and height > width):
        tan_x *= width / height
    m = get_matrix(obj)
    finish(obj)
    reader.builder.add_projector_light(m[:3, 3], m[:3, :3] @ np.array([0.0, 0.0, 1.0]),
                                       m[:3, :3] @ np.array([1.0, 0.0, 0.0]), irradiance,
                                       tan_x, obj.where(), texture)


# Read apart from point and spot (no `intensity`).
INFINITE = {"directional": _directional, "constant": _constant, "envmap": _envmap, "projector": _projector}
