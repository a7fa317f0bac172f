"""Built-in scenes of renderers' known failure modes, for comparing speed
against accuracy. Each is built from nothing in milliseconds, in the
Cornell scenes' units (mm, +y up), at 256x256 pixels, from the Cornell
box's parts where they use it (`cornell.py`); `builtin.make(name)` builds
them by name.

| name                | what goes wrong in a renderer            | the right answer                  |
|---------------------|------------------------------------------|-----------------------------------|
| `thin-wall`         | photon gathers reach through a thin wall | the camera's room is black        |
| `far-from-origin`   | float32 positions 1e5 mm from the origin | the image of `cornell-box`        |
| `many-lights`       | light choice among 400 lamps of 4 powers | soft light, noise as for one lamp |
| `glossy-floor`      | SPPM converges slowly on a GGX floor     | a blurred reflection, no blotches |
| `glass-small-light` | a 20 mm lamp inside a glass lantern      | a room lit by caustics alone      |
| `cardioid`          | a point light's caustic off a mirror ring | a bright cardioid on the floor   |

Each function's docstring gives the layout and what it tests; its keyword
arguments vary the scene (the built-in names use the defaults).
"""
from __future__ import annotations

import numpy as np

from dosppm_core.scene import shapes
from dosppm_core.scene.cornell import (
    CORNELL_BLOCKS,
    CORNELL_LIGHT_RADIANCE,
    CORNELL_REFLECTANCE,
    CORNELL_SHELL,
    cornell_builder,
    cornell_part,
)
from dosppm_core.scene.model import Camera, Material, Scene, SceneBuilder

# Cornell's measured luminaire (130 x 105 mm): the power every lit scene
# here matches, so their images are about as bright as `cornell-box`.
CORNELL_LIGHT_AREA_MM2 = 130.0 * 105.0
WHITE = CORNELL_REFLECTANCE["white"]
LIGHT_REFLECTANCE = CORNELL_REFLECTANCE["light"]

THIN_WALL_ROOM_MM = 550.0       # each room is a cube of this side
THIN_WALL_MM = 5.5              # 1% of the room
FAR_OFFSET_MM = (1e5, 1e5, 1e5)
GLOSSY_FLOOR_ROUGHNESS = 0.15


# -- mesh helpers -------------------------------------------------------------

def rectangle_mesh(centre, half_u, half_v) -> tuple[np.ndarray, np.ndarray]:
    """The rectangle centre +- half_u +- half_v, facing half_u x half_v
    (an emissive material emits that way)."""
    c, u, v = (np.asarray(a, np.float64) for a in (centre, half_u, half_v))
    vertices = np.array([c - u - v, c + u - v, c + u + v, c - u + v])
    return vertices, shapes.quads_to_triangles(np.arange(4).reshape(1, 4))


def box_mesh(lo, hi, inward: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The axis-aligned closed box [lo, hi], facing out, or in: a room."""
    vertices, faces = shapes.box()
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    vertices = lo + (vertices + 1.0) / 2.0 * (hi - lo)
    return vertices, (faces[:, ::-1] if inward else faces)


def _block_mesh(size, yaw_deg: float, centre_xz) -> tuple[np.ndarray, np.ndarray]:
    """A closed box of `size` (x, y, z), turned `yaw_deg` about +y and
    standing on the floor at `centre_xz`."""
    vertices, faces = shapes.box()
    vertices = (vertices * np.asarray(size, np.float64) / 2.0) @ shapes.rotation_matrix((0, 1, 0), yaw_deg).T
    return vertices + (centre_xz[0], size[1] / 2.0, centre_xz[1]), faces


def _lamp_material(name: str, radiance) -> Material:
    return Material(name, "diffuse", reflectance=LIGHT_REFLECTANCE, emission=tuple(radiance),
                    two_sided=False)


def _cornell_light_scaled(area_mm2: float) -> np.ndarray:
    """Cornell's light radiance scaled so `area_mm2` of it emits the
    Cornell luminaire's power."""
    return np.asarray(CORNELL_LIGHT_RADIANCE) * (CORNELL_LIGHT_AREA_MM2 / area_mm2)


# -- the scenes ---------------------------------------------------------------

def thin_wall(thickness_mm: float = THIN_WALL_MM, lit_side: bool = False) -> Scene:
    """Two rooms side by side, cubes of 550 mm, parted by one diffuse wall
    `thickness_mm` thick (1% of the room). Room A (x < 550) holds a
    Cornell-sized luminaire under its ceiling; the camera (fov 60) stands
    in room B against its far wall, looking at the wall's B side.

    Tests light leaks. Both rooms are closed: the outer shell is one box
    facing in, and the wall is a closed box of its own (both faces exist)
    reaching `thickness_mm` into the shell's floor, ceiling and sides, so
    no ray crosses from one room to the other, and the exact image is
    black. A photon map leaks where a gather radius longer than the wall
    is thick reaches photons on room A's floor, ceiling or sides from the
    matching surface in room B: a bright seam along the wall's edges.

    `lit_side=True` puts the camera in room A instead, looking at the wall's
    A side from the mirrored place: the radiance a leak is measured against.
    """
    t, room = float(thickness_mm), THIN_WALL_ROOM_MM
    wall_lo, wall_hi = room, room + t
    builder = SceneBuilder(source="builtin:thin-wall", name="thin-wall")
    builder.add_material(Material("white", "diffuse", reflectance=WHITE))
    builder.add_material(Material("wall", "diffuse", reflectance=WHITE))
    builder.add_material(_lamp_material("light", CORNELL_LIGHT_RADIANCE))
    builder.add_mesh(*box_mesh((0.0, 0.0, 0.0), (2 * room + t, room, room), inward=True), "white",
                     "builtin:thin-wall: rooms")
    builder.add_mesh(*box_mesh((wall_lo, -t, -t), (wall_hi, room + t, room + t)), "wall",
                     "builtin:thin-wall: wall")
    builder.add_mesh(*rectangle_mesh((room / 2, room - 0.5, room / 2), (65.0, 0.0, 0.0), (0.0, 0.0, 52.5)),
                     "light", "builtin:thin-wall: luminaire in room A")
    middle = room / 2
    if lit_side:
        eye, target = (10.0, middle, middle), (wall_lo, middle, middle)
    else:
        eye, target = (wall_hi + room - 10.0, middle, middle), (wall_hi, middle, middle)
    builder.camera = Camera(position=eye, look_at=target, up=(0.0, 1.0, 0.0), fov_deg=60.0,
                            width=256, height=256)
    return builder.build()


def far_from_origin(offset_mm=FAR_OFFSET_MM) -> Scene:
    """`cornell-box` with every vertex and the camera moved by `offset_mm`
    (1e5 mm along each axis): the same triangles in the same order.

    Tests float32 precision. At 1e5 float32 steps are 1/128 mm, so any
    offset that does not grow with |p| vanishes; a renderer that loses
    precision far from the origin shows acne, light leaking under the
    blocks or a darker image. The right answer is `cornell-box`'s image.
    (dosppm fails it for now: photons leave the lamp a fixed 0.001 mm off
    it and all hit its black back; see tests/test_suite_scenes.py.)
    """
    return cornell_builder("far-from-origin", CORNELL_SHELL + CORNELL_BLOCKS,
                           offset_mm=tuple(float(x) for x in offset_mm)).build()


def many_lights(lamps_across: int = 20) -> Scene:
    """A closed white room (800 x 400 x 800 mm) holding three diffuse
    blocks, lit by `lamps_across`^2 square lamps (12 mm, 400 by default)
    0.5 mm under the ceiling, facing down. The lamps come in four radiances
    1 : 3 : 9 : 27, mixed across the ceiling, together emitting the Cornell
    luminaire's power.

    Tests light selection with hundreds of lights: emission must pick a
    lamp in proportion to its power (the light table's `cdf`); picking
    uniformly, or only the brightest, gives a wrong or noisy image. The
    camera (fov 70) stands inside the front wall and sees most lamps.
    """
    size = np.array([800.0, 400.0, 800.0])
    builder = SceneBuilder(source="builtin:many-lights", name="many-lights")
    builder.add_material(Material("white", "diffuse", reflectance=WHITE))
    builder.add_material(Material("block", "diffuse", reflectance=CORNELL_REFLECTANCE["box"]))
    builder.add_mesh(*box_mesh((0.0, 0.0, 0.0), size, inward=True), "white", "builtin:many-lights: room")
    for block_size, yaw, centre_xz in (((200.0, 240.0, 160.0), 20.0, (250.0, 450.0)),
                                       ((120.0, 120.0, 120.0), -30.0, (560.0, 300.0)),
                                       ((300.0, 80.0, 150.0), 5.0, (480.0, 620.0))):
        builder.add_mesh(*_block_mesh(block_size, yaw, centre_xz), "block", "builtin:many-lights: block")
    _add_lamp_grid(builder, size, int(lamps_across), half_mm=6.0)
    builder.camera = Camera(position=(400.0, 150.0, 5.0), look_at=(400.0, 230.0, 800.0),
                            up=(0.0, 1.0, 0.0), fov_deg=70.0, width=256, height=256)
    return builder.build()


def _add_lamp_grid(builder: SceneBuilder, room_mm: np.ndarray, across: int, half_mm: float) -> None:
    """`across` x `across` square lamps centred in the cells of the ceiling,
    in four radiance levels 1 : 3 : 9 : 27 assigned by (7i + 3j) mod 4, so
    each level holds a quarter of the lamps in every row, scaled to the
    Cornell luminaire's power in all."""
    levels = 3.0 ** np.arange(4)
    i, j = np.meshgrid(np.arange(across), np.arange(across), indexing="ij")
    level = (7 * i + 3 * j) % 4
    lamp_area = (2 * half_mm) ** 2
    # Power is pi * area * mean radiance: scale so the sum is Cornell's.
    unit = _cornell_light_scaled(lamp_area * levels[level].sum())
    for k, factor in enumerate(levels):
        builder.add_material(_lamp_material(f"light-{k}", unit * factor))
    cell = room_mm[[0, 2]] / across
    y = room_mm[1] - 0.5
    for a, b in zip(i.ravel(), j.ravel()):
        centre = ((a + 0.5) * cell[0], y, (b + 0.5) * cell[1])
        builder.add_mesh(*rectangle_mesh(centre, (half_mm, 0.0, 0.0), (0.0, 0.0, half_mm)),
                         f"light-{level[a, b]}", f"builtin:many-lights: lamp ({a}, {b})")


def glossy_floor(roughness: float = GLOSSY_FLOOR_ROUGHNESS) -> Scene:
    """`cornell-box` whose floor is glossy: one GGX lobe of `roughness`
    (alpha, 0.15 by default) tinted like the white walls, one-sided as the
    other Cornell surfaces.

    Tests glossy convergence: a photon map blurs the floor's reflection of
    the blocks and walls over the gather radius, and SPPM converges slowly
    on a near-specular surface, where a path tracer samples the lobe well.
    """
    parts = tuple(p for p in CORNELL_SHELL if p != "floor") + CORNELL_BLOCKS
    builder = cornell_builder("glossy-floor", parts)
    builder.add_material(Material("glossy", "glossy", reflectance=WHITE, roughness=float(roughness),
                                  two_sided=False))
    builder.add_mesh(*cornell_part("floor"), "glossy", "builtin:glossy-floor: floor")
    return builder.build()


def glass_small_light(lamp_mm: float = 20.0, lantern_mm: float = 120.0, pane_mm: float = 6.0) -> Scene:
    """A closed white room (a 560 mm cube) lit only by a small lamp: a cube
    of side `lamp_mm` emitting from all six faces, floating at mid-height
    inside a hollow glass lantern (ior 1.5), a cube of side `lantern_mm`
    with walls `pane_mm` thick (an outer box facing out and an inner one
    facing in, so both sides of every pane exist). The lamp emits the
    Cornell luminaire's power; the camera (fov 55) looks down at it.

    Tests a small light behind glass: every light path leaves through two
    refractions, so the whole room is lit by caustics (a path tracer's
    shadow rays towards the lamp all stop at the glass and find nothing),
    and the lamp itself is seen only through a pane, at its true size,
    about 17 pixels across at 256x256.
    """
    room, centre = 560.0, np.array([280.0, 250.0, 330.0])
    builder = SceneBuilder(source="builtin:glass-small-light", name="glass-small-light")
    builder.add_material(Material("white", "diffuse", reflectance=WHITE))
    builder.add_material(Material("glass", "glass", reflectance=(1.0, 1.0, 1.0), ior=1.5))
    builder.add_material(_lamp_material("light", _cornell_light_scaled(6 * float(lamp_mm) ** 2)))
    builder.add_mesh(*box_mesh((0.0, 0.0, 0.0), (room, room, room), inward=True), "white",
                     "builtin:glass-small-light: room")
    outer, inner = float(lantern_mm) / 2, float(lantern_mm) / 2 - float(pane_mm)
    builder.add_mesh(*box_mesh(centre - outer, centre + outer), "glass",
                     "builtin:glass-small-light: lantern, outside")
    builder.add_mesh(*box_mesh(centre - inner, centre + inner, inward=True), "glass",
                     "builtin:glass-small-light: lantern, inside")
    half = float(lamp_mm) / 2
    builder.add_mesh(*box_mesh(centre - half, centre + half), "light", "builtin:glass-small-light: lamp")
    builder.camera = Camera(position=(280.0, 420.0, 20.0), look_at=tuple(float(x) for x in centre),
                            up=(0.0, 1.0, 0.0), fov_deg=55.0, width=256, height=256)
    return builder.build()


def cardioid(segments: int = 128, radius_mm: float = 300.0, height_mm: float = 60.0) -> Scene:
    """MNRT's cardioid scene, made procedurally: an open ring of mirror
    (`segments` facets, `radius_mm`, `height_mm` tall, mirror on both
    sides) standing on a grey floor 2 m square, lit by one point light
    above and to the side of the ring, seen from above at an angle.

    Tests a caustic from a point light (light-specular-diffuse-eye): the
    cardioid that the ring's inside focuses onto the floor. A path tracer
    cannot render it at all: a floor point's paths reach the light only
    through the mirror, and a point light cannot be hit. Light tracing
    (Mitsuba's `ptracer`) renders the floor; the mirror itself, seen by
    the camera, needs `path`.
    """
    builder = SceneBuilder(source="builtin:cardioid", name="cardioid")
    builder.add_material(Material("floor", "diffuse", reflectance=(0.5, 0.5, 0.5), two_sided=False))
    builder.add_material(Material("mirror", "mirror", reflectance=(0.9, 0.85, 0.6)))
    builder.add_mesh(*rectangle_mesh((0.0, 0.0, 0.0), (0.0, 0.0, 1000.0), (1000.0, 0.0, 0.0)),
                     "floor", "builtin:cardioid: floor")
    angle = np.linspace(0.0, 2 * np.pi, int(segments), endpoint=False)
    ring = np.stack([radius_mm * np.cos(angle), np.zeros_like(angle), radius_mm * np.sin(angle)], 1)
    vertices = np.concatenate([ring, ring + (0.0, float(height_mm), 0.0)])
    n = len(angle)
    i = np.arange(n)
    j = (i + 1) % n
    faces = np.concatenate([np.stack([i, n + i, j], 1), np.stack([j, n + i, n + j], 1)])
    builder.add_mesh(vertices, faces, "mirror", "builtin:cardioid: ring")
    # Intensity L * A of Cornell's luminaire (radiance L, area A): the floor
    # under the light is then about as bright as the Cornell box's walls.
    intensity = np.asarray(CORNELL_LIGHT_RADIANCE) * CORNELL_LIGHT_AREA_MM2
    builder.add_point_light((0.0, 250.0, 450.0), tuple(intensity), "builtin:cardioid: light")
    builder.camera = Camera(position=(0.0, 700.0, -500.0), look_at=(0.0, 0.0, 0.0),
                            up=(0.0, 1.0, 0.0), fov_deg=60.0, width=256, height=256)
    return builder.build()
