"""Built-in procedural scenes: no files needed, each built in milliseconds.

| name                | what it is                                                        |
|---------------------|-------------------------------------------------------------------|
| `cornell-box`       | the measured Cornell box, exactly as Mitsuba's `cbox-rgb.xml`      |
| `cornell-caustic`   | the box with a glass and a mirror sphere instead of the two blocks |
| `cornell-glass`     | the box with a 110k-triangle glass torus knot (the default)        |
| `furnace-sphere`    | a diffuse sphere lit from its centre: radiance in closed form      |
| `thin-wall`         | two closed rooms parted by a 5.5 mm wall, lit on one side only     |
| `far-from-origin`   | `cornell-box` moved by (1e5, 1e5, 1e5) mm, camera and all          |
| `many-lights`       | a room lit by 400 small ceiling lamps of four powers               |
| `glossy-floor`      | `cornell-box` with a GGX floor of roughness 0.15                   |
| `glass-small-light` | a room lit by a 20 mm lamp inside a hollow glass lantern           |

The last five are the suite of renderers' known failure modes (light leaks,
float32 precision, light selection, glossy surfaces, small lights behind
glass); `suite_scenes.py` builds them and says what each one tests.

The Cornell geometry is the Cornell Program of Computer Graphics' measured
data in millimetres, +y up, as in Mitsuba's `meshes/cbox_*.obj`: the same
vertices, the same quad triangulation and the same winding, so a Mitsuba
render of `cbox-rgb.xml` is a like-for-like reference.
"""
from __future__ import annotations

import os

import numpy as np

from dosppm_core.scene import shapes
from dosppm_core.scene.model import Camera, Material, Scene, SceneBuilder, SceneError

SCENES = {
    "cornell-box": "the measured Cornell box with its two blocks (Mitsuba's cbox-rgb.xml)",
    "cornell-caustic": "the Cornell box with a glass sphere and a mirror sphere (caustics)",
    "cornell-glass": "the Cornell box holding a 110k-triangle glass torus knot (stand-in for the Cornell dragon)",
    "furnace-sphere": "a closed diffuse sphere lit by a point light at its centre (closed-form radiance)",
    "thin-wall": "two closed rooms parted by a wall 1% thick, one lit; the other must stay black (light leaks)",
    "far-from-origin": "cornell-box moved 1e5 mm along each axis, to render the same (float32 precision)",
    "many-lights": "a room lit by 400 small ceiling lamps of four powers (light selection by power)",
    "glossy-floor": "cornell-box with a glossy GGX floor of roughness 0.15 (slow SPPM convergence)",
    "glass-small-light": "a 20 mm lamp inside a glass lantern: seen through glass, the room lit by caustics",
    "cardioid": "a point light's cardioid caustic off a mirror ring (a path tracer cannot render it)",
}
DEFAULT = "cornell-glass"

# -- the measured Cornell box ------------------------------------------------
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


def cornell_box() -> Scene:
    """The measured Cornell box with its two blocks, 38 triangles."""
    return cornell_builder("cornell-box", CORNELL_SHELL + CORNELL_BLOCKS).build()


def _placed(vertices: np.ndarray, scale: float, rotation: np.ndarray,
            centre_xz: tuple[float, float], floor_gap_mm: float) -> np.ndarray:
    """Scale and rotate an object-space mesh, then move it so its bounding
    box is centred at `centre_xz` and its lowest point `floor_gap_mm` above
    the floor (a small gap keeps it from touching the floor exactly)."""
    v = (vertices * scale) @ rotation.T
    lo, hi = v.min(axis=0), v.max(axis=0)
    offset = np.array([centre_xz[0] - (lo[0] + hi[0]) / 2, floor_gap_mm - lo[1],
                       centre_xz[1] - (lo[2] + hi[2]) / 2])
    return v + offset


def cornell_caustic(subdivisions: int = 6) -> Scene:
    """The box with, instead of the blocks, a mirror sphere at the back
    left and a glass sphere (ior 1.5) at the front right, laid out like
    Nori's `cbox-pmap.xml` photon-mapping scene rescaled to the measured box.
    Both spheres have radius 100 mm, 1 mm above the floor, and
    20 * 4**subdivisions triangles each (81,920 by default)."""
    builder = cornell_builder("cornell-caustic", CORNELL_SHELL)
    builder.add_material(Material("mirror", "mirror", reflectance=(1.0, 1.0, 1.0)))
    builder.add_material(Material("glass", "glass", reflectance=(1.0, 1.0, 1.0), ior=1.5))
    vertices, faces = shapes.ico_sphere(subdivisions)
    for mat, centre_xz in (("mirror", (391.0, 350.0)), ("glass", (152.0, 169.0))):
        placed = _placed(vertices, 100.0, np.eye(3), centre_xz, 1.0)
        builder.add_mesh(placed, faces, mat, f"builtin:cornell-caustic: {mat} sphere")
    return builder.build()


def cornell_glass() -> Scene:
    """The box (no blocks) holding `shapes.glass_knot()` in glass (ior 1.5),
    110,592 triangles: the stand-in for the paper's Cornell dragon. The knot
    is about 330 mm across, stands facing the camera, tilted 30 degrees back
    towards the light, and rests 1 mm above the floor."""
    builder = cornell_builder("cornell-glass", CORNELL_SHELL)
    builder.add_material(Material("glass", "glass", reflectance=(1.0, 1.0, 1.0), ior=1.5))
    vertices, faces = shapes.glass_knot()
    # The knot lies in its xy-plane; turning it about z puts a lobe on top,
    # tilting about x leans it back so light from above passes through it.
    rotation = shapes.rotation_matrix((1, 0, 0), 30.0) @ shapes.rotation_matrix((0, 0, 1), 90.0)
    placed = _placed(vertices, 100.0, rotation, (278.0, 300.0), 1.0)
    builder.add_mesh(placed, faces, "glass", "builtin:cornell-glass: glass knot")
    return builder.build()


def cornell_with_mesh(path: str, size_mm: float = 330.0) -> Scene:
    """The box (no blocks) holding the mesh file `path` (any format trimesh
    reads) in glass, scaled so its largest side is `size_mm`, centred and
    resting 1 mm above the floor: how `dosppm bench --mesh` places the
    Stanford dragon, like the paper's Cornell dragon scene."""
    from dosppm_core.scene.tomlfile import load_mesh_file
    name = f"cornell-{os.path.splitext(os.path.basename(path))[0]}"
    vertices, faces = load_mesh_file(path, path, "mesh")
    builder = cornell_builder(name, CORNELL_SHELL)
    builder.add_material(Material("glass", "glass", reflectance=(1.0, 1.0, 1.0), ior=1.5))
    extent = float(np.ptp(vertices, axis=0).max())
    if not extent > 0.0:
        raise SceneError(f"{path}: mesh has no extent")
    placed = _placed(vertices, size_mm / extent, np.eye(3), (278.0, 280.0), 1.0)
    builder.add_mesh(placed, faces, "glass", f"{path}: mesh")
    return builder.build()


def furnace_sphere(albedo: float = 0.5, intensity: float = 1.0, subdivisions: int = 5) -> Scene:
    """A closed diffuse sphere (radius R = 1, albedo rho, two-sided) with a
    point light of intensity I (W/sr) and the camera at its centre looking
    out (32x32 pixels, 60 degrees field of view).

    The irradiance from the light is I / R^2 everywhere, and a sphere's
    interior exchanges light uniformly, so every point has the same radiance
    after each bounce. With infinite bounces the exact radiance seen is

        L = rho * I / (pi * R^2 * (1 - rho)),

    and with paths limited to depth D (D surface interactions, the first one
    being the visible one) it is the partial sum

        L_D = rho * I / (pi * R^2) * sum_{k < D} rho^k.

    The sphere is an icosphere with `subdivisions` levels (20,480 triangles
    at 5) and vertices on the unit sphere; its flat faces lie at most
    0.03% inside it, which changes the first-bounce radiance by less than
    0.06% (at 5 levels) -- below the noise of any test.
    """
    builder = SceneBuilder(source="builtin:furnace-sphere", name="furnace-sphere")
    builder.camera = Camera(position=(0.0, 0.0, 0.0), look_at=(0.0, 0.0, 1.0), up=(0.0, 1.0, 0.0),
                            fov_deg=60.0, width=32, height=32)
    builder.add_material(Material("wall", "diffuse", reflectance=(albedo,) * 3, two_sided=True))
    vertices, faces = shapes.ico_sphere(subdivisions)
    builder.add_mesh(vertices, faces, "wall", "builtin:furnace-sphere: sphere")
    builder.add_point_light((0.0, 0.0, 0.0), (intensity,) * 3, "builtin:furnace-sphere: light")
    return builder.build()


def _suite(function: str):
    """A maker for a scene of `suite_scenes`, imported on first use: that
    module builds on the Cornell helpers above, so it imports this one."""
    def make_suite_scene() -> Scene:
        from dosppm_core.scene import suite as suite_scenes
        return getattr(suite_scenes, function)()
    return make_suite_scene


_MAKERS = {
    "cornell-box": cornell_box,
    "cornell-caustic": cornell_caustic,
    "cornell-glass": cornell_glass,
    "furnace-sphere": furnace_sphere,
    "thin-wall": _suite("thin_wall"),
    "far-from-origin": _suite("far_from_origin"),
    "many-lights": _suite("many_lights"),
    "glossy-floor": _suite("glossy_floor"),
    "glass-small-light": _suite("glass_small_light"),
    "cardioid": _suite("cardioid"),
}


def make(name: str) -> Scene:
    """Build the built-in scene `name` (one of `SCENES`)."""
    try:
        maker = _MAKERS[name]
    except KeyError:
        raise SceneError(f"unknown built-in scene {name!r} (known: {', '.join(SCENES)})") from None
    return maker()
