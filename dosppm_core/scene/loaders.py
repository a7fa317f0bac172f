"""One entry point from a user's scene argument to a `Scene`: a built-in
name, a TOML scene file or a Mitsuba 3 XML file; and to a `TriangleSource`,
which may also be a triangle soup directory too big for memory."""
from __future__ import annotations

import os

from dosppm_core.scene import builtin
from dosppm_core.scene.mitsuba import load_mitsuba_xml
from dosppm_core.scene.model import Scene, SceneError
from dosppm_core.scene.soup import SceneSource
from dosppm_core.scene.soupfile import is_soup, open_soup
from dosppm_core.scene.tomlfile import load_toml


def load_scene(spec: str, params: dict | None = None, **overrides) -> Scene:
    """`overrides` may set `width` and `height` of the camera; `params` are
    a Mitsuba file's `$name` parameters (`{"spp": 16}`, like Mitsuba's
    ``-D spp=16``), overriding its `<default>`s."""
    if params and not str(spec).lower().endswith(".xml"):
        raise SceneError(f"{spec}: parameters {', '.join(params)} given, but only a Mitsuba .xml file takes them")
    if spec in builtin.SCENES:
        scene = builtin.make(spec)
    else:
        if not os.path.exists(spec):
            raise SceneError(f"{spec}: no such file, and not a built-in scene "
                             f"(built-in: {', '.join(builtin.SCENES)})")
        ext = os.path.splitext(spec)[1].lower()
        if os.path.isdir(spec):
            raise SceneError(f"{spec}: a directory, but neither a chunk store nor a triangle soup "
                             f"(it has no manifest)")
        if ext == ".toml":
            scene = load_toml(spec)
        elif ext == ".xml":
            scene = load_mitsuba_xml(spec, **(params or {}))
        else:
            raise SceneError(f"{spec}: unknown scene format {ext!r} (expected .toml or .xml)")
    for key in ("width", "height"):
        if overrides.get(key):
            setattr(scene.camera, key, int(overrides[key]))
    return scene


def load_source(spec: str, params: dict | None = None):
    """A `TriangleSource`: a soup directory is memory-mapped, anything else
    is loaded by `load_scene` (with a Mitsuba file's `params`) and wrapped."""
    if is_soup(spec) and not params:
        return open_soup(spec)
    return SceneSource(load_scene(spec, params))
