"""The measured Cornell box: its parts, materials and camera, which the
built-in scenes (`builtin`) and the failure-mode suite (`suite`) build on.

The geometry is the Cornell Program of Computer Graphics' measured data in
millimetres, +y up, as in Mitsuba's `meshes/cbox_*.obj`: the same vertices,
the same quad triangulation and the same winding, so a Mitsuba render of
`cbox-rgb.xml` is a like-for-like reference.
"""
from __future__ import annotations

import numpy as np

from dosppm_core.scene import shapes
from dosppm_core.scene.model import Camera, Material, SceneBuilder

# Each part is a list of quads, each quad four (x, y, z) corners in mm, in
# the order of Mitsuba's OBJ files: counter-clockwise seen from the lit side,
# so walls face into the box and the blocks face out. Quads are split as
# (a, b, c) + (a, c, d), as trimesh and Mitsuba split them.
_CORNELL_PARTS = {
    "floor": [[(552.8, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 559.2), (549.6, 0.0, 559.2)]],
    # The second ceiling quad is the light's footprint with reversed winding
    # (facing up, out of the box), coplanar with the first. It is hidden: the
    # luminaire covers it from 0.5 mm below, so only rays through that 0.5 mm
    # slit can reach it, and light and photons never do in practice. It is
    # kept so the triangle set equals Mitsuba's and comparisons stay exact.
    "ceiling": [[(556.0, 548.8, 0.0), (556.0, 548.8, 559.2), (0.0, 548.8, 559.2), (0.0, 548.8, 0.0)],
                [(213.0, 548.8, 227.0), (213.0, 548.8, 332.0), (343.0, 548.8, 332.0), (343.0, 548.8, 227.0)]],
    "back": [[(549.6, 0.0, 559.2), (0.0, 0.0, 559.2), (0.0, 548.8, 559.2), (556.0, 548.8, 559.2)]],
    "greenwall": [[(0.0, 0.0, 559.2), (0.0, 0.0, 0.0), (0.0, 548.8, 0.0), (0.0, 548.8, 559.2)]],
    "redwall": [[(552.8, 0.0, 0.0), (549.6, 0.0, 559.2), (556.0, 548.8, 559.2), (556.0, 548.8, 0.0)]],
    "smallbox": [
        [(130, 165, 65), (82, 165, 225), (240, 165, 272), (290, 165, 114)],
        [(290, 0, 114), (290, 165, 114), (240, 165, 272), (240, 0, 272)],
        [(130, 0, 65), (130, 165, 65), (290, 165, 114), (290, 0, 114)],
        [(82, 0, 225), (82, 165, 225), (130, 165, 65), (130, 0, 65)],
        [(240, 0, 272), (240, 165, 272), (82, 165, 225), (82, 0, 225)],
        [(290, 0, 114), (240, 0, 272), (82, 0, 225), (130, 0, 65)]],
    "largebox": [
        [(423, 330, 247), (265, 330, 296), (314, 330, 456), (472, 330, 406)],
        [(423, 0, 247), (423, 330, 247), (472, 330, 406), (472, 0, 406)],
        [(472, 0, 406), (472, 330, 406), (314, 330, 456), (314, 0, 456)],
        [(314, 0, 456), (314, 330, 456), (265, 330, 296), (265, 0, 296)],
        [(265, 0, 296), (265, 330, 296), (423, 330, 247), (423, 0, 247)],
        [(472, 0, 406), (314, 0, 456), (265, 0, 296), (423, 0, 247)]],
    # Listed facing down (-y), its emitting side; Mitsuba lowers it by 0.5 mm.
    "luminaire": [[(343.0, 548.8, 227.0), (343.0, 548.8, 332.0), (213.0, 548.8, 332.0), (213.0, 548.8, 227.0)]],
}
_LUMINAIRE_OFFSET_MM = (0.0, -0.5, 0.0)
_PART_MATERIAL = {"floor": "white", "ceiling": "white", "back": "white", "greenwall": "green",
                  "redwall": "red", "smallbox": "box", "largebox": "box", "luminaire": "light"}

# Mitsuba's fragments/bsdfs-rgb.xml and the area emitter of cbox-rgb.xml.
# Mitsuba's diffuse BSDF is black from behind, hence two_sided=False.
CORNELL_REFLECTANCE = {
    "white": (0.885809, 0.698859, 0.666422),
    "red": (0.570068, 0.0430135, 0.0443706),
    "green": (0.105421, 0.37798, 0.076425),
    "box": (0.45, 0.30, 0.90),
    "light": (0.936461, 0.740433, 0.705267),
}
CORNELL_LIGHT_RADIANCE = (18.387, 10.9873, 2.75357)


def cornell_part(name: str) -> tuple[np.ndarray, np.ndarray]:
    """One part of the measured Cornell box (see `_CORNELL_PARTS`) as
    (vertices in mm, triangles), the luminaire already lowered by 0.5 mm."""
    quads = np.asarray(_CORNELL_PARTS[name], np.float64)
    vertices = quads.reshape(-1, 3)
    if name == "luminaire":
        vertices = vertices + _LUMINAIRE_OFFSET_MM
    faces = shapes.quads_to_triangles(np.arange(len(vertices)).reshape(-1, 4))
    return vertices, faces


def cornell_camera(width: int = 256, height: int = 256) -> Camera:
    """The Cornell camera (35 mm lens on 25 mm film), as in Mitsuba's cbox."""
    return Camera(position=(278.0, 273.0, -800.0), look_at=(278.0, 273.0, -799.0),
                  up=(0.0, 1.0, 0.0), fov_deg=39.3077, width=width, height=height,
                  fov_axis="smaller")


def cornell_builder(name: str, parts: tuple[str, ...],
                    offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> SceneBuilder:
    """A builder holding the Cornell camera, materials and the given parts
    (see `_CORNELL_PARTS`), everything moved by `offset_mm`; more meshes and
    materials may be added before `build()`."""
    builder = SceneBuilder(source=f"builtin:{name}", name=name)
    offset = np.asarray(offset_mm, np.float64)
    camera = cornell_camera()
    camera.position = tuple(float(x) for x in np.add(camera.position, offset))
    camera.look_at = tuple(float(x) for x in np.add(camera.look_at, offset))
    builder.camera = camera
    used = {_PART_MATERIAL[part] for part in parts}
    for mat, refl in CORNELL_REFLECTANCE.items():
        if mat not in used:
            continue
        emission = CORNELL_LIGHT_RADIANCE if mat == "light" else (0.0, 0.0, 0.0)
        builder.add_material(Material(mat, "diffuse", reflectance=refl, emission=emission,
                                      two_sided=False))
    for part in parts:
        vertices, faces = cornell_part(part)
        builder.add_mesh(vertices + offset, faces, _PART_MATERIAL[part], f"builtin:{name}: {part}")
    return builder


# The box without its blocks, and the blocks.
CORNELL_SHELL = ("floor", "ceiling", "back", "greenwall", "redwall", "luminaire")
CORNELL_BLOCKS = ("smallbox", "largebox")
