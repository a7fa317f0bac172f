"""Nori's dialect of the scene XML (no ``version``, ``<mesh>``,
``<camera>``, ``<color>``), rewritten in place to the Mitsuba elements it
means: camelCase names, albedo, mirror, a film for width/height, the
top-level sampler. Nori's image x axis runs opposite to Mitsuba's, so a
Nori camera gets ``scale(-1, 1, 1)`` applied first; Nori's defaults (fov
30, 1280x720) are made explicit."""
from __future__ import annotations

import numpy as np

from dosppm_core.scene.mitsuba.objects import upgrade_names
from dosppm_core.scene.mitsuba.values import numbers
from dosppm_core.scene.mitsuba.xmltree import Node, synthetic, walk

_NORI_ONLY_TAGS = {"mesh", "camera", "color"}
_NORI_TAGS = {"mesh": "shape", "camera": "sensor", "color": "rgb"}


def dialect(root: Node) -> str:
    """'mitsuba' or 'nori'."""
    if root.tag != "scene":
        root.fail("the root element must be <scene>")
    if "version" in root.attrib:
        return "mitsuba"
    if any(node.tag in _NORI_ONLY_TAGS for node in walk(root)):
        return "nori"
    root.fail('missing version attribute (Mitsuba 3 scenes start with <scene version="3.0.0">)')


def nori_to_mitsuba(root: Node) -> None:
    upgrade_names(root)
    for node in walk(root):
        node.tag = _NORI_TAGS.get(node.tag, node.tag)
        kind = node.attrib.get("type")
        if node.tag == "bsdf" and kind == "mirror":
            node.attrib["type"] = "conductor"
        if node.tag == "bsdf" and kind == "diffuse":
            for prop in node.children:
                if prop.attrib.get("name") == "albedo":
                    prop.attrib["name"] = "reflectance"
        if node.tag == "rotate" and "axis" in node.attrib:      # Nori normalises its axes
            axis = numbers(node, node.attrib.pop("axis"), (3,))
            node.attrib["value"] = " ".join(map(repr, axis / (np.linalg.norm(axis) or 1.0)))
    samplers = [c for c in root.children if c.tag == "sampler"]
    cameras = [c for c in root.children if c.tag == "sensor"]
    for camera in cameras:
        _nori_camera(camera, samplers if camera is cameras[0] else [])
    if cameras:
        root.children = [c for c in root.children if c not in samplers]


def _nori_camera(camera: Node, samplers: list) -> None:
    """Width, height and rfilter move into a film; Nori's defaults are made
    explicit; its image x axis runs along camera +x where Mitsuba's runs along
    -x, so the camera-to-world gets scale(-1, 1, 1) applied first."""
    film = synthetic("film", {"type": "hdrfilm"}, camera)
    size = {"width": "1280", "height": "720"}
    kept = []
    for child in camera.children:
        if child.tag == "rfilter" or (child.tag == "integer" and child.attrib.get("name") in size):
            film.children.append(child)
            size.pop(child.attrib.get("name"), None)
        else:
            kept.append(child)
    film.children += [synthetic("integer", {"name": k, "value": v}, camera) for k, v in size.items()]
    names = {c.attrib.get("name") for c in kept}
    for name, value in (("fov", "30"), ("near_clip", "1e-4"), ("far_clip", "1e4")):
        if name not in names:
            kept.append(synthetic("float", {"name": name, "value": value}, camera))
    to_world = next((c for c in kept if c.tag == "transform" and c.attrib.get("name") == "to_world"), None)
    if to_world is None:
        to_world = synthetic("transform", {"name": "to_world"}, camera)
        kept.append(to_world)
    to_world.children.insert(0, synthetic("scale", {"x": "-1"}, to_world))
    camera.children = kept + [film] + samplers
