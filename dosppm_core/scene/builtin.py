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
| `cardioid`          | a point light's caustic off a mirror ring                          |

The last six are the suite of renderers' known failure modes (light leaks,
float32 precision, light selection, glossy surfaces, small lights behind
glass, point-light caustics); `suite.py` builds them and says what each one
tests. The Cornell box itself (measured geometry, materials, camera) is in
`cornell.py`.

This module is the one registry of named scenes: `SCENES` (name -> one-line
description), `DEFAULT`, and `make(name)`.
"""
from __future__ import annotations

import os

import numpy as np

from dosppm_core.scene import shapes, suite
from dosppm_core.scene.cornell import CORNELL_BLOCKS, CORNELL_SHELL, cornell_builder
from dosppm_core.scene.model import Camera, Material, Scene, SceneBuilder, SceneError
from dosppm_core.scene.tomlfile import load_mesh_file


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
    name = f"cornell-{os.path.splitext(os.path.basename(path))[0]}"
    vertices, faces, _uv = load_mesh_file(path, path, "mesh")    # a glass mesh reads no texture
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


# -- the registry: name -> (maker, one-line description), in listing order ------

_REGISTRY = {
    "cornell-box": (cornell_box, "the measured Cornell box with its two blocks (Mitsuba's cbox-rgb.xml)"),
    "cornell-caustic": (cornell_caustic, "the Cornell box with a glass sphere and a mirror sphere (caustics)"),
    "cornell-glass": (cornell_glass, "the Cornell box holding a 110k-triangle glass torus knot "
                                     "(stand-in for the Cornell dragon)"),
    "furnace-sphere": (furnace_sphere, "a closed diffuse sphere lit by a point light at its centre "
                                       "(closed-form radiance)"),
    "thin-wall": (suite.thin_wall, "two closed rooms parted by a wall 1% thick, one lit; "
                                   "the other must stay black (light leaks)"),
    "far-from-origin": (suite.far_from_origin, "cornell-box moved 1e5 mm along each axis, to render "
                                               "the same (float32 precision)"),
    "many-lights": (suite.many_lights, "a room lit by 400 small ceiling lamps of four powers "
                                       "(light selection by power)"),
    "glossy-floor": (suite.glossy_floor, "cornell-box with a glossy GGX floor of roughness 0.15 "
                                         "(slow SPPM convergence)"),
    "glass-small-light": (suite.glass_small_light, "a 20 mm lamp inside a glass lantern: seen through "
                                                   "glass, the room lit by caustics"),
    "cardioid": (suite.cardioid, "a point light's cardioid caustic off a mirror ring "
                                 "(a path tracer cannot render it)"),
}
SCENES = {name: description for name, (_, description) in _REGISTRY.items()}
DEFAULT = "cornell-glass"


def make(name: str) -> Scene:
    """Build the built-in scene `name` (one of `SCENES`)."""
    try:
        maker, _ = _REGISTRY[name]
    except KeyError:
        raise SceneError(f"unknown built-in scene {name!r} (known: {', '.join(SCENES)})") from None
    return maker()
