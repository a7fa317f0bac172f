"""Emitters: `area` (its radiance becomes the emission of the material of
the shape holding or referencing it), `point` and `spot`."""
from __future__ import annotations

import numpy as np

from dosppm_core.scene.mitsuba.objects import Obj
from dosppm_core.scene.mitsuba.params import finish, get_float, get_matrix, get_point, get_rgb
from dosppm_core.scene.mitsuba.state import ReaderState


def area_radiance(reader: ReaderState, emitter: Obj) -> tuple:
    """The RGB radiance of an area emitter attached to a shape."""
    if emitter.type != "area":
        emitter.node.fail("only area emitters can be attached to a shape")
    if id(emitter) not in reader.radiance:
        reader.children(emitter, ())
        reader.radiance[id(emitter)] = get_rgb(emitter, "radiance", 1.0)
        finish(emitter)
    return reader.radiance[id(emitter)]


def read_emitter(reader: ReaderState, obj: Obj) -> None:
    """An emitter at scene level."""
    if obj.type == "area":                # a definition: some shape must reference it
        reader.loose_area_emitters.append(obj)
        return
    reader.children(obj, ())
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
    finish(obj)
    target = m[:3, 3] + m[:3, :3] @ np.array([0.0, 0.0, 1.0])
    reader.builder.add_spot_light(m[:3, 3], target, intensity, cutoff, beam, obj.where())
