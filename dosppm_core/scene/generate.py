"""`building`: a procedural office building, the stand-in for the paper's
MPI building (623 lights, tens of millions of triangles), written as a
triangle soup far larger than one process's memory.

| parameter   | default | meaning                                                       |
|-------------|---------|---------------------------------------------------------------|
| `triangles` | 1M      | target triangle count, met within a fraction of a percent     |
| `lights`    | 600     | ceiling area lights (emissive quads of two triangles each)    |
| `rooms`     | auto    | (rows, cols) per floor; auto gives about 5 lights per room    |
| `floors`    | 2       | storeys; rooms connect through doors within a floor           |
| `seed`      | 0       | the same seed gives the same soup, byte for byte              |
| `width`, `height` | 256 | camera resolution                                          |

Layout (metres, +y up, Mitsuba's convention): room (floor f, row r, col c)
fills the cell [c W, (c+1) W] x [f H, (f+1) H] x [r D, (r+1) D]. Walls and
slabs are `WALL` thick: each room's surfaces are inset by half of that and
face into the room, and every interior wall has a door whose reveal (two
jambs, lintel, threshold) each room builds half of, meeting the neighbour's
half on the cell boundary. So every room is generated on its own, the
building is closed, and no ray ever enters a wall. Ceiling lights hang 1 cm
below the ceiling, emitting downward (their counter-clockwise front).
Tables and cabinets are boxes whose faces are tessellated, and every room
holds glass objects (ico spheres and torus knots, ior 1.5); the triangle
budget goes to these two, the last knot of each room taking the remainder,
so the count is hit to within a few hundred triangles per room.

Streaming: `plan_building` decides everything small (doors, lights,
placements, triangles per object; a few hundred bytes a room), then rooms
are emitted one by one in blocks of at most `SLICE` triangles; big knots are
emitted in slices of their tube. Peak memory is a few blocks, whatever the
size of the soup. Vertices shared by two slices are computed by the same
element-wise arithmetic from the same per-ring data, so the tube stays
watertight across slices.

    dosppm scenes generate building --triangles 20M --lights 600 --out building/
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from dosppm_core.scene import shapes
from dosppm_core.scene.building_geometry import KNOT_TUBE, flat, knot_slices, rects, tessellated_box
from dosppm_core.scene.model import (
    Camera,
    Material,
    MaterialTable,
    Scene,
    SceneBuilder,
    SceneError,
    SceneHeader,
    light_table,
)
from dosppm_core.scene.soupfile import CORNERS, MANIFEST, MATERIAL, SoupWriter

# -- dimensions (metres) -------------------------------------------------------
ROOM_W, ROOM_D, ROOM_H = 6.0, 6.0, 3.0     # cell size along x, z and y
WALL = 0.2                                  # wall and slab thickness
DOOR_W, DOOR_H = 1.2, 2.2
DOOR_MARGIN = 0.4                           # least wall beside a door
DOOR_CLEAR = 1.2                            # kept free of furniture in front of a door
LIGHT_SIZE, LIGHT_DROP = 0.5, 0.01          # light quad side; gap below the ceiling
LIGHTS_PER_ROOM = 5                         # for the automatic room grid
GAP = 0.001                                 # objects float this far above what carries them

LIGHT_RADIANCE = (12.0, 10.8, 9.0)          # warm white
SLICE = 1 << 16                             # triangles per emitted block
FURNITURE_SHARE = 0.3                       # of a room's free budget, the rest is glass
MAX_TESSELLATION = 48                       # grid per box face (12 * 48^2 = 27,648 triangles)
MAX_SPHERE_LEVEL = 6                        # 81,920 triangles
KNOT_MIN = (24, 6)                          # (tubular, radial): 288 triangles
KNOT_MAX_RADIAL = 192
KNOT_ASPECT = 768 / 72                      # tubular / radial of shapes.torus_knot


def building_materials() -> list[Material]:
    """The building's materials; their order gives the material ids."""
    return [
        Material("wall", "diffuse", reflectance=(0.78, 0.76, 0.72)),
        Material("ceiling", "diffuse", reflectance=(0.85, 0.85, 0.85)),
        Material("floor", "diffuse", reflectance=(0.45, 0.36, 0.28)),
        Material("light", "diffuse", reflectance=(0.8, 0.8, 0.8), emission=LIGHT_RADIANCE,
                 two_sided=False),
        Material("wood", "diffuse", reflectance=(0.50, 0.33, 0.20)),
        Material("lacquer", "glossy", reflectance=(0.70, 0.55, 0.40), roughness=0.3),
        Material("fabric-red", "diffuse", reflectance=(0.60, 0.12, 0.10)),
        Material("fabric-blue", "diffuse", reflectance=(0.12, 0.20, 0.55)),
        Material("metal", "glossy", reflectance=(0.85, 0.85, 0.85), roughness=0.08),
        Material("mirror", "mirror", reflectance=(0.9, 0.9, 0.9)),
        Material("glass", "glass", reflectance=(1.0, 1.0, 1.0), ior=1.5),
        Material("glass-tinted", "glass", reflectance=(0.80, 0.95, 1.0), ior=1.5),
    ]


_IDS = {m.name: i for i, m in enumerate(building_materials())}
WALL_ID, CEILING_ID, FLOOR_ID, LIGHT_ID = (_IDS[n] for n in ("wall", "ceiling", "floor", "light"))
TABLE_IDS = tuple(_IDS[n] for n in ("wood", "lacquer", "metal"))
CABINET_IDS = tuple(_IDS[n] for n in ("wood", "lacquer", "fabric-red", "fabric-blue", "metal", "mirror"))
GLASS_IDS = (_IDS["glass"], _IDS["glass-tinted"])


# -- the specification ----------------------------------------------------------

@dataclass
class BuildingSpec:
    triangles: int = 1_000_000
    lights: int = 600
    rooms: tuple | None = None      # (rows, cols) per floor; None: about 5 lights a room
    floors: int = 2
    seed: int = 0
    width: int = 256
    height: int = 256

    def validate(self) -> None:
        for name in ("triangles", "lights", "floors", "width", "height"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise SceneError(f"building: {name} must be a positive integer, got {value!r}")
        if self.rooms is not None and (len(self.rooms) != 2 or min(self.rooms) < 1):
            raise SceneError(f"building: rooms must be (rows, cols) >= 1, got {self.rooms!r}")
        if not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise SceneError(f"building: seed must be a non-negative integer, got {self.seed!r}")

    def grid(self) -> tuple[int, int]:
        """(rows, cols) per floor: as given, or a near-square grid with
        about `LIGHTS_PER_ROOM` lights per room."""
        if self.rooms is not None:
            return int(self.rooms[0]), int(self.rooms[1])
        n = max(1, math.ceil(self.lights / (LIGHTS_PER_ROOM * self.floors)))
        rows = max(1, math.isqrt(n))
        return rows, math.ceil(n / rows)

    def describe(self) -> str:
        rows, cols = self.grid()
        return (f"generate:building triangles={self.triangles} lights={self.lights} "
                f"rooms={rows}x{cols} floors={self.floors} seed={self.seed}")


# -- the plan: everything small, decided before any triangle is made -------------

@dataclass
class Door:
    """An opening in the wall at `lo[axis]` (sign -1) or `hi[axis]` (+1) of a
    room, spanning [d0, d1] along the wall and DOOR_H up from the floor."""
    axis: int       # 0: wall normal to x, 2: wall normal to z
    sign: int
    d0: float
    d1: float


@dataclass
class GlassObject:
    kind: str                   # 'sphere' or 'knot'
    centre_xz: tuple
    base_y: float               # what it stands on (floor or table top)
    size: float                 # sphere radius, or knot scale
    yaw_deg: float
    material: int
    detail: tuple = ()          # sphere: (level,); knot: (tubular, radial)

    def triangle_count(self) -> int:
        if self.kind == "sphere":
            return 20 * 4 ** self.detail[0]
        return 2 * self.detail[0] * self.detail[1]


@dataclass
class RoomPlan:
    index: int
    cell: tuple                 # (floor, row, col)
    lo: np.ndarray              # interior box, float64 (3,)
    hi: np.ndarray
    doors: list
    lights: np.ndarray          # light triangle corners, float64 (2k, 3, 3)
    boxes: list = field(default_factory=list)    # (lo, hi, material) furniture boxes
    glass: list = field(default_factory=list)    # GlassObject
    tessellation: int = 1

    def shell_triangle_count(self) -> int:
        """Floor, ceiling, walls (3 quads around a door, else 1) and half reveals."""
        return 4 + 2 * 4 + 12 * len(self.doors)

    def triangle_count(self) -> int:
        return (self.shell_triangle_count() + len(self.lights)
                + 12 * self.tessellation ** 2 * len(self.boxes)
                + sum(g.triangle_count() for g in self.glass))


@dataclass
class BuildingPlan:
    spec: BuildingSpec
    rooms: list
    camera: Camera

    @property
    def triangle_count(self) -> int:
        return sum(r.triangle_count() for r in self.rooms)

    def light_corners(self) -> np.ndarray:
        """All light triangles, rounded to float32 as they are written."""
        return np.concatenate([r.lights for r in self.rooms]).astype(np.float32)

    def header(self, bounds: np.ndarray) -> SceneHeader:
        mats = MaterialTable.from_materials(building_materials())
        corners = self.light_corners().astype(np.float64)
        radiance = np.tile(np.asarray(LIGHT_RADIANCE, np.float64), (len(corners), 1))
        lights = light_table(corners[:, 0], corners[:, 1], corners[:, 2], radiance)
        return SceneHeader(mats, lights, self.camera, np.asarray(bounds, np.float64), "building",
                           self.spec.describe(), {})


def plan_building(spec: BuildingSpec) -> BuildingPlan:
    """Rooms, doors, lights, camera, placements and triangles per object."""
    spec.validate()
    rows, cols = spec.grid()
    rng = np.random.default_rng([spec.seed, 0])
    doors_x, doors_z = _door_centres(rng, spec.floors, rows, cols)
    per_room = _lights_per_room(spec.lights, spec.floors * rows * cols)
    rooms = []
    for f in range(spec.floors):
        for r in range(rows):
            for c in range(cols):
                index = (f * rows + r) * cols + c
                lo = np.array([c * ROOM_W, f * ROOM_H, r * ROOM_D]) + WALL / 2
                hi = np.array([(c + 1) * ROOM_W, (f + 1) * ROOM_H, (r + 1) * ROOM_D]) - WALL / 2
                doors = _room_doors(f, r, c, rows, cols, doors_x, doors_z)
                rooms.append(RoomPlan(index, (f, r, c), lo, hi, doors,
                                      _light_quads(lo, hi, per_room[index])))
    camera, view = _camera(spec, rooms[0])
    budgets = _split(spec.triangles, len(rooms))
    for room, budget in zip(rooms, budgets):
        _furnish(room, budget, np.random.default_rng([spec.seed, 1, room.index]),
                 view if room.index == 0 else None)
    _check_budget(spec, rooms)
    return BuildingPlan(spec, rooms, camera)


def _door_centres(rng, floors: int, rows: int, cols: int):
    """Door centre along each interior wall: doors_x[f, r, c] (along z) in the
    wall between columns c and c+1, doors_z[f, r, c] (along x) between rows
    r and r+1. Rounded to the centimetre, as a builder would."""
    reach = lambda cell: cell / 2 - WALL / 2 - DOOR_MARGIN - DOOR_W / 2  # noqa: E731
    ux = rng.uniform(-reach(ROOM_D), reach(ROOM_D), (floors, rows, max(cols - 1, 0)))
    uz = rng.uniform(-reach(ROOM_W), reach(ROOM_W), (floors, max(rows - 1, 0), cols))
    doors_x = np.round((np.arange(rows) + 0.5)[None, :, None] * ROOM_D + ux, 2)
    doors_z = np.round((np.arange(cols) + 0.5)[None, None, :] * ROOM_W + uz, 2)
    return doors_x, doors_z


def _room_doors(f, r, c, rows, cols, doors_x, doors_z) -> list[Door]:
    doors = []
    for axis, sign, ok, centre in (
            (0, -1, c > 0, lambda: doors_x[f, r, c - 1]),
            (0, +1, c + 1 < cols, lambda: doors_x[f, r, c]),
            (2, -1, r > 0, lambda: doors_z[f, r - 1, c]),
            (2, +1, r + 1 < rows, lambda: doors_z[f, r, c])):
        if ok:
            mid = float(centre())
            doors.append(Door(axis, sign, mid - DOOR_W / 2, mid + DOOR_W / 2))
    return doors


def _lights_per_room(lights: int, rooms: int) -> np.ndarray:
    """An even share each, the first rooms (the camera's first) one more."""
    counts = np.full(rooms, lights // rooms)
    counts[: lights % rooms] += 1
    return counts


def _light_quads(lo, hi, count: int) -> np.ndarray:
    """`count` square lights on a grid over the ceiling, facing down."""
    if count == 0:
        return np.empty((0, 3, 3))
    ncol = math.ceil(math.sqrt(count))
    nrow = math.ceil(count / ncol)
    sx, sz = (hi[0] - lo[0]) / ncol, (hi[2] - lo[2]) / nrow
    half = min(LIGHT_SIZE, 0.6 * min(sx, sz)) / 2
    i = np.arange(count)
    cx, cz = lo[0] + (i % ncol + 0.5) * sx, lo[2] + (i // ncol + 0.5) * sz
    y = np.full(count, hi[1] - LIGHT_DROP)
    qlo = np.stack([cx - half, y, cz - half], 1)
    qhi = np.stack([cx + half, y, cz + half], 1)
    return rects(1, qlo, qhi, -1)


def _camera(spec: BuildingSpec, room: RoomPlan) -> tuple[Camera, tuple]:
    """A camera 4 m before a door of the first room, a little off its
    axis, looking through it into the next room; and where furniture must
    not stand in its room (see `_view_area`)."""
    lo, hi = room.lo, room.hi
    door = next((d for d in room.doors if d.sign > 0), None)
    if door is None:  # a single room: look across it from a corner
        pos = np.array([lo[0] + 0.5, lo[1] + 1.6, lo[2] + 0.5])
        look = np.array([hi[0], lo[1] + 0.8, hi[2]])
    else:
        a, t = door.axis, 2 - door.axis
        mid = (door.d0 + door.d1) / 2
        side = 1.0 if mid < (lo[t] + hi[t]) / 2 else -1.0
        pos, look = np.empty(3), np.empty(3)
        pos[a], pos[t], pos[1] = hi[a] - 4.0, mid + 1.2 * side, lo[1] + 1.6
        look[a], look[t], look[1] = hi[a] + 2.0, mid, lo[1] + 1.0
    cam = Camera(position=tuple(map(float, pos)), look_at=tuple(map(float, look)),
                 up=(0.0, 1.0, 0.0), fov_deg=70.0, width=spec.width, height=spec.height)
    return cam, _view_area(room, pos[[0, 2]], look[[0, 2]])


def _view_area(room: RoomPlan, pos, look) -> tuple[list, tuple]:
    """Floor squares along the line of sight (kept free, so the door stays
    visible), and a 1 m square 2.6 m ahead and 25 degrees aside where the
    room's first glass object stands in view; the side with more room."""
    length = float(np.linalg.norm(look - pos))
    u = (look - pos) / length
    sight = [(c - 0.4, c + 0.4) for c in pos + u[None] * np.arange(0.0, length, 0.4)[:, None]]
    best = None
    for angle in (math.radians(25), -math.radians(25)):
        cos, sin = math.cos(angle), math.sin(angle)
        spot = pos + 2.6 * np.array([u[0] * cos - u[1] * sin, u[0] * sin + u[1] * cos])
        margin = min(np.min(spot - room.lo[[0, 2]]), np.min(room.hi[[0, 2]] - spot))
        if best is None or margin > best[0]:
            best = (margin, spot)
    return sight, (best[1] - 0.5, best[1] + 0.5)


def _split(total: int, parts: int) -> list[int]:
    base, extra = divmod(total, parts)
    return [base + (i < extra) for i in range(parts)]


# -- furnishing a room: placement, then the triangle budget ----------------------

@lru_cache(maxsize=None)
def _knot_reach() -> float:
    """Horizontal reach of the upright knot (turned 90 degrees about z, as
    placed) from its axis, in object units, with a 2% margin for sampling."""
    centre, _ = shapes.torus_knot_curve(np.linspace(0, 2 * np.pi, 4096, endpoint=False))
    return 1.02 * float(np.hypot(centre[:, 1], centre[:, 2]).max()) + KNOT_TUBE


def _taken_area(room: RoomPlan, sight: list) -> list:
    """Floor rectangles (xz lo, hi) that furniture must not cover: the space
    before every door, so rooms stay connected, and the camera's view."""
    taken = []
    for d in room.doors:
        a, t = d.axis, 2 - d.axis
        lo, hi = np.empty(3), np.empty(3)
        wall = room.hi[a] if d.sign > 0 else room.lo[a]
        lo[a], hi[a] = sorted((wall, wall - d.sign * DOOR_CLEAR))
        lo[t], hi[t] = d.d0 - 0.3, d.d1 + 0.3
        taken.append((lo[[0, 2]], hi[[0, 2]]))
    return taken + list(sight)


def _place(rng, room: RoomPlan, taken: list, half: tuple, tries: int = 40, within=None):
    """A random free spot for a footprint of half sizes `half` (x, z), or
    None; the footprint is added to `taken`. `within` (xz lo, hi) limits
    where its centre may be."""
    lo = room.lo[[0, 2]] + np.asarray(half) + 0.1
    hi = room.hi[[0, 2]] - np.asarray(half) - 0.1
    if within is not None:
        lo, hi = np.maximum(lo, within[0]), np.minimum(hi, within[1])
    if np.any(lo > hi):
        return None
    for _ in range(tries):
        c = rng.uniform(lo, hi)
        flo, fhi = c - half, c + half
        if all(np.any(flo > thi + 0.15) or np.any(fhi < tlo - 0.15) for tlo, thi in taken):
            taken.append((flo, fhi))
            return c
    return None


def _furnish(room: RoomPlan, budget: int, rng, view) -> None:
    """Place glass objects, tables and cabinets, then share the room's
    triangles between them. The first glass object stands on the still
    empty floor, so every room has one (it takes the budget's remainder);
    in the camera's room (`view`: line of sight, stage) it stands in view."""
    taken = _taken_area(room, view[0] if view else [])
    floor = room.lo[1]
    free = budget - room.shell_triangle_count() - len(room.lights)
    wanted = int(rng.integers(1, 4))
    n_glass = max(1, min(wanted, free // 2000))
    _place_floor_glass(rng, room, taken, "knot", view[1] if view else None)
    tables = []
    for _ in range(int(rng.integers(1, 3))):
        top = _place_table(rng, room, taken)
        if top is not None:
            tables.append(top)
    for _ in range(n_glass - 1):
        kind = ("sphere", "knot")[int(rng.integers(2))]
        if tables and rng.random() < 0.6:
            _place_table_glass(rng, room, tables.pop(), kind)
        else:
            _place_floor_glass(rng, room, taken, kind)
    for _ in range(int(rng.integers(1, 4))):
        hx, hz = rng.uniform(0.25, 0.6), rng.uniform(0.2, 0.3)
        if rng.random() < 0.5:
            hx, hz = hz, hx
        c = _place(rng, room, taken, (hx, hz))
        if c is not None:
            lo = np.array([c[0] - hx, floor + GAP, c[1] - hz])
            hi = np.array([c[0] + hx, floor + rng.uniform(0.8, 2.0), c[1] + hz])
            room.boxes.append((lo, hi, CABINET_IDS[int(rng.integers(len(CABINET_IDS)))]))
    _allocate(room, budget)


def _place_floor_glass(rng, room: RoomPlan, taken: list, kind: str, within=None) -> None:
    if kind == "sphere":
        size = rng.uniform(0.25, 0.45)
        reach = size
    else:
        size = rng.uniform(0.2, 0.28)      # 0.7 to 1.0 m tall
        reach = size * _knot_reach()
    c = _place(rng, room, taken, (reach, reach), tries=200, within=within)
    if c is None and within is not None:
        c = _place(rng, room, taken, (reach, reach), tries=200)
    if c is None and not room.glass:       # cannot happen in a 5.8 m room; be safe
        c = (room.lo[[0, 2]] + room.hi[[0, 2]]) / 2
    if c is not None:
        room.glass.append(GlassObject(kind, (float(c[0]), float(c[1])), float(room.lo[1]), size,
                                      float(rng.uniform(0, 360)), _glass_material(rng)))


def _place_table(rng, room: RoomPlan, taken: list):
    """A table: a top slab on four legs. Returns its top (xz centre, half
    sizes, height) for an object to stand on, or None if it did not fit."""
    hx, hz = rng.uniform(0.5, 0.9), rng.uniform(0.35, 0.5)
    if rng.random() < 0.5:
        hx, hz = hz, hx
    c = _place(rng, room, taken, (hx, hz))
    if c is None:
        return None
    floor, material = room.lo[1], TABLE_IDS[int(rng.integers(len(TABLE_IDS)))]
    top_y = floor + 0.75
    room.boxes.append((np.array([c[0] - hx, top_y - 0.05, c[1] - hz]),
                       np.array([c[0] + hx, top_y, c[1] + hz]), material))
    for sx in (-1, 1):
        for sz in (-1, 1):
            lx, lz = c[0] + sx * (hx - 0.08), c[1] + sz * (hz - 0.08)
            room.boxes.append((np.array([lx - 0.03, floor + GAP, lz - 0.03]),
                               np.array([lx + 0.03, top_y - 0.05, lz + 0.03]), material))
    return c, min(hx, hz), top_y


def _place_table_glass(rng, room: RoomPlan, table, kind: str) -> None:
    (cx, cz), half, top_y = table
    room_for = half - 0.05
    size = min(rng.uniform(0.12, 0.2), room_for) if kind == "sphere" else \
        min(rng.uniform(0.08, 0.12), room_for / _knot_reach())
    room.glass.append(GlassObject(kind, (float(cx), float(cz)), float(top_y), float(size),
                                  float(rng.uniform(0, 360)), _glass_material(rng)))


def _glass_material(rng) -> int:
    return GLASS_IDS[0] if rng.random() < 0.75 else GLASS_IDS[1]


def _allocate(room: RoomPlan, budget: int) -> None:
    """Share what the shell and lights leave: FURNITURE_SHARE to the box
    tessellation, an equal share to each glass object but the first, and
    the remainder to the first (a knot, whose size is free to the triangle)."""
    free = budget - room.shell_triangle_count() - len(room.lights)
    if room.boxes:
        per_box = FURNITURE_SHARE * free / (12 * len(room.boxes))
        room.tessellation = int(np.clip(math.isqrt(max(int(per_box), 1)), 1, MAX_TESSELLATION))
    glass = free - 12 * room.tessellation ** 2 * len(room.boxes)
    share = glass / len(room.glass)
    for obj in room.glass[1:]:
        if obj.kind == "sphere":
            level = int(np.clip(math.floor(math.log(max(share, 20) / 20, 4)), 1, MAX_SPHERE_LEVEL))
            obj.detail = (level,)
        else:
            obj.detail = _knot_detail(share)
    rest = glass - sum(g.triangle_count() for g in room.glass[1:])
    room.glass[0].detail = _knot_detail(rest)


def _knot_detail(count: float) -> tuple[int, int]:
    """(tubular, radial) segments for about `count` triangles, of the aspect
    of shapes.torus_knot (nearly square quads), off by at most `radial`."""
    radial = int(np.clip(round(math.sqrt(max(count, 1) / (2 * KNOT_ASPECT))), KNOT_MIN[1], KNOT_MAX_RADIAL))
    tubular = max(KNOT_MIN[0], round(count / (2 * radial)))
    return tubular, radial


def _check_budget(spec: BuildingSpec, rooms: list) -> None:
    """A budget too small for the shells, lights and one coarse knot per
    room is overshot; past 5% that is an error saying what would do."""
    least = 2 * KNOT_MIN[0] * KNOT_MIN[1]
    need = max(r.shell_triangle_count() + len(r.lights) + 12 * len(r.boxes) + least for r in rooms)
    made = sum(r.triangle_count() for r in rooms)
    if abs(made - spec.triangles) > 0.05 * spec.triangles:
        raise SceneError(f"building: {spec.triangles:,} triangles are too few for {len(rooms)} rooms "
                         f"and {spec.lights} lights; need at least {need * len(rooms):,}")


# -- geometry: triangle corners, float64 (m, 3, 3) (see building_geometry) ---------

def _shell(room: RoomPlan) -> tuple[np.ndarray, np.ndarray]:
    """Floor, ceiling, walls with door holes and half reveals, all facing
    into the room."""
    lo, hi = room.lo, room.hi
    parts = [(rects(1, *flat(lo, hi, 1, lo[1]), +1), FLOOR_ID),
             (rects(1, *flat(lo, hi, 1, hi[1]), -1), CEILING_ID)]
    doors = {(d.axis, d.sign): d for d in room.doors}
    for axis in (0, 2):
        for sign in (-1, 1):
            parts.append((_wall(room, axis, sign, doors.get((axis, sign))), WALL_ID))
    for d in room.doors:
        parts.append((_half_reveal(room, d), WALL_ID))
    corners = np.concatenate([p for p, _ in parts])
    material = np.concatenate([np.full(len(p), m, np.int32) for p, m in parts])
    return corners, material


def _wall(room: RoomPlan, axis: int, sign: int, door: Door | None) -> np.ndarray:
    """The wall at lo[axis] (sign -1) or hi[axis] (+1), facing -sign (into
    the room); with a door, the three pieces around the opening."""
    lo, hi, t = room.lo, room.hi, 2 - axis
    value = hi[axis] if sign > 0 else lo[axis]
    if door is None:
        return rects(axis, *flat(lo, hi, axis, value), -sign)
    pieces = []
    for t0, t1, y0 in ((lo[t], door.d0, lo[1]), (door.d1, hi[t], lo[1]),
                       (door.d0, door.d1, lo[1] + DOOR_H)):
        plo, phi = flat(lo, hi, axis, value)
        plo[t], phi[t], plo[1] = t0, t1, y0
        pieces.append(rects(axis, plo, phi, -sign))
    return np.concatenate(pieces)


def _half_reveal(room: RoomPlan, door: Door) -> np.ndarray:
    """The room's half of the door opening, from its wall surface to the
    cell boundary WALL/2 further: two jambs, lintel and threshold, facing
    into the opening."""
    a, t = door.axis, 2 - door.axis
    wall = room.hi[a] if door.sign > 0 else room.lo[a]
    lo, hi = np.empty(3), np.empty(3)
    lo[a], hi[a] = sorted((wall, wall + door.sign * WALL / 2))
    lo[t], hi[t] = door.d0, door.d1
    lo[1], hi[1] = room.lo[1], room.lo[1] + DOOR_H
    return np.concatenate([rects(t, *flat(lo, hi, t, door.d0), +1),
                           rects(t, *flat(lo, hi, t, door.d1), -1),
                           rects(1, *flat(lo, hi, 1, hi[1]), -1),
                           rects(1, *flat(lo, hi, 1, lo[1]), +1)])


_unit_sphere = lru_cache(maxsize=MAX_SPHERE_LEVEL + 1)(shapes.ico_sphere)  # shared by every room


def _sphere(obj: GlassObject) -> np.ndarray:
    """The glass ico sphere, resting GAP above its base, in one piece."""
    vertices, faces = _unit_sphere(obj.detail[0])
    rot = shapes.rotation_matrix((0, 1, 0), obj.yaw_deg)
    centre = np.array([obj.centre_xz[0], obj.base_y + GAP + obj.size, obj.centre_xz[1]])
    # Flat faces lie inside the unit sphere, so nothing dips below the base.
    return ((vertices * obj.size) @ rot.T + centre)[faces]


def _knot_slices(obj: GlassObject):
    """The glass knot, resting GAP above its base, in slices of its tube of
    at most SLICE triangles."""
    tubular, radial = obj.detail
    return knot_slices(tubular, radial, obj.size, obj.yaw_deg, obj.centre_xz, obj.base_y + GAP, SLICE)


def _room_pieces(room: RoomPlan):
    """(corners float64 (m, 3, 3), material id or ids) of one room, in
    order: shell, lights, furniture, glass; no piece over SLICE triangles."""
    yield _shell(room)
    if len(room.lights):
        yield room.lights, LIGHT_ID
    for lo, hi, material in room.boxes:
        yield tessellated_box(lo, hi, room.tessellation), material
    for obj in room.glass:
        if obj.kind == "sphere":
            yield _sphere(obj), obj.material
        else:
            for piece in _knot_slices(obj):
                yield piece, obj.material


class _Blocks:
    """Gathers pieces into blocks of about SLICE triangles for `sink`, so
    that small pieces do not become small writes."""

    def __init__(self, sink):
        self.sink, self.parts, self.count = sink, [], 0

    def add(self, corners: np.ndarray, material) -> None:
        self.parts.append((corners.astype(np.float32),
                           np.broadcast_to(np.asarray(material, np.int32), (len(corners),))))
        self.count += len(corners)
        if self.count >= SLICE:
            self.flush()

    def flush(self) -> None:
        if self.parts:
            self.sink(np.concatenate([c for c, _ in self.parts]),
                      np.concatenate([m for _, m in self.parts]))
        self.parts, self.count = [], 0


def emit_building(plan: BuildingPlan, sink) -> None:
    """Call `sink(corners float32 (m, 3, 3), material int32 (m,))` for every
    block of the building, room by room."""
    blocks = _Blocks(sink)
    for room in plan.rooms:
        for corners, material in _room_pieces(room):
            blocks.add(corners, material)
    blocks.flush()


# -- the two products: a soup on disk, a Scene in memory ---------------------------

@dataclass
class GenerateReport:
    path: str
    triangles: int
    lights: int
    rooms: int
    bytes: int
    seconds: float
    content_hash: str


def generate_building(out_dir: str, triangles: int = 1_000_000, lights: int = 600,
                      rooms: tuple | None = None, floors: int = 2, seed: int = 0,
                      width: int = 256, height: int = 256) -> GenerateReport:
    """Write the building as a triangle soup in `out_dir` (see soupfile),
    streaming: memory stays a few blocks whatever `triangles` is."""
    start = time.perf_counter()
    plan = plan_building(BuildingSpec(triangles, lights, rooms, floors, seed, width, height))
    writer = SoupWriter(out_dir)
    emit_building(plan, writer.append)
    digest = writer.close(plan.header(np.stack([writer.lo, writer.hi])))
    size = sum(os.path.getsize(os.path.join(out_dir, n)) for n in (MANIFEST, CORNERS, MATERIAL))
    return GenerateReport(out_dir, writer.count, lights, len(plan.rooms), size,
                          time.perf_counter() - start, digest)


def building_scene(triangles: int = 200_000, lights: int = 24, rooms: tuple | None = None,
                   floors: int = 1, seed: int = 0, width: int = 256, height: int = 256) -> Scene:
    """The same building as an in-memory `Scene`, for sizes that fit."""
    spec = BuildingSpec(triangles, lights, rooms, floors, seed, width, height)
    plan = plan_building(spec)
    blocks = []
    emit_building(plan, lambda c, m: blocks.append((c, m)))
    corners = np.concatenate([c for c, _ in blocks])
    material = np.concatenate([m for _, m in blocks])
    builder = SceneBuilder(source=spec.describe(), name="building")
    for m in building_materials():
        builder.add_material(m)
    for mid in np.unique(material):
        sel = corners[material == mid].reshape(-1, 3)
        builder.add_mesh(sel, np.arange(len(sel)).reshape(-1, 3), int(mid), f"building: material {mid}")
    builder.camera = plan.camera
    return builder.build()
