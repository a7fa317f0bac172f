"""`load_mitsuba_xml`: parse, expand, read. The file is parsed
(`xmltree`), a Nori file rewritten to Mitsuba's elements (`nori`), the
object tree built with includes and `$parameters` (`objects`), then each
scene-level object handed to its plugin family's reader."""
from __future__ import annotations

import os

from dosppm_core.scene.mitsuba.bsdfs import bsdf_material
from dosppm_core.scene.mitsuba.emitters import read_emitter
from dosppm_core.scene.mitsuba.nori import dialect as file_dialect
from dosppm_core.scene.mitsuba.nori import nori_to_mitsuba
from dosppm_core.scene.mitsuba.objects import (
    NORI_PLUGINS,
    PLUGINS,
    Expander,
    Obj,
    Ref,
    upgrade_names,
    version,
)
from dosppm_core.scene.mitsuba.params import finish
from dosppm_core.scene.mitsuba.sensors import read_integrator, read_sensor
from dosppm_core.scene.mitsuba.shapes import read_shape
from dosppm_core.scene.mitsuba.state import ReaderState
from dosppm_core.scene.mitsuba.textures import read_texture
from dosppm_core.scene.mitsuba.xmltree import parse_xml
from dosppm_core.scene.model import Scene, SceneError

# The scene-level objects and who reads them.
_READERS = {"shape": read_shape, "sensor": read_sensor, "integrator": read_integrator,
            "bsdf": bsdf_material, "emitter": read_emitter, "texture": read_texture}


def load_mitsuba_xml(path: str, **defaults) -> Scene:
    """Load a Mitsuba 3 (or Nori) scene file. Keyword arguments override the
    file's `<default>` parameters, like `mitsuba.load_file(path, spp=16)`.
    Settings with no home in `Scene` go to `scene.render_settings`."""
    path = os.fspath(path)
    root = parse_xml(path)
    dialect = file_dialect(root)
    if dialect == "nori":
        nori_to_mitsuba(root)
    elif version(root) < (2, 0, 0):
        upgrade_names(root)
    expander = Expander(path, defaults, NORI_PLUGINS if dialect == "nori" else PLUGINS)
    expander.substitute(root)
    scene = expander.object(root)
    unused = expander.unused_params()
    if unused:
        raise SceneError(f"{path}: parameter(s) {', '.join(unused)} given but never used as $name in the file")
    return read_scene(ReaderState(path, expander.ids, dialect, expander.paths), scene)


def read_scene(reader: ReaderState, scene: Obj) -> Scene:
    """Interpret the object tree into `SceneBuilder` calls and build."""
    for child in scene.children:
        if isinstance(child, Ref) or child.tag not in _READERS:
            child.node.fail("not supported at scene level")
        _READERS[child.tag](reader, child)
    finish(scene)
    for emitter in reader.loose_area_emitters:
        if id(emitter) not in reader.radiance:
            emitter.node.fail("area emitter is not attached to any shape")
    result = reader.builder.build()
    result.render_settings = reader.settings
    return result
