"""The generated building: counts as asked, deterministic, closed and
correctly wound, rooms connected through their doors, renderable, and
written in bounded memory whatever its size."""
import numpy as np
import pytest

from dosppm_core.accel import MISS, Accelerator
from dosppm_core.scene import generate
from dosppm_core.scene.generate import BuildingSpec, building_scene, generate_building, plan_building
from dosppm_core.scene.model import GLASS, LIGHT_TRIANGLE, SceneError
from dosppm_core.scene.soupfile import open_soup
from services.cli import scenes as scenes_cli
from tests.helpers.cli import run_dosppm, run_python


def _normals(corners):
    c = np.asarray(corners, np.float64)
    n = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _all_corners(source):
    blocks = list(source.blocks())
    return np.concatenate([c for _, c, _ in blocks]), np.concatenate([m for _, _, m in blocks])


@pytest.mark.parametrize("triangles, lights", [(100_000, 12), (400_000, 60), (1_500_000, 623)])
def test_counts_are_as_asked(tmp_path, triangles, lights):
    report = generate_building(str(tmp_path / "b"), triangles=triangles, lights=lights)
    soup = open_soup(str(tmp_path / "b"))
    assert soup.count == report.triangles
    assert abs(soup.count - triangles) <= 0.1 * triangles
    table = soup.header.lights
    assert np.all(table.kind == LIGHT_TRIANGLE) and len(table.kind) == 2 * lights
    _, material = _all_corners(soup)
    assert np.count_nonzero(material == generate.LIGHT_ID) == 2 * lights


def test_same_seed_same_soup_other_seed_differs(tmp_path):
    hashes = [generate_building(str(tmp_path / str(i)), triangles=60_000, lights=20, seed=seed).content_hash
              for i, seed in enumerate((7, 7, 8))]
    assert hashes[0] == hashes[1] != hashes[2]


def test_soup_is_valid_and_lights_hang_from_ceilings_facing_down(tmp_path):
    generate_building(str(tmp_path / "b"), triangles=200_000, lights=40, rooms=(2, 2), floors=2)
    soup = open_soup(str(tmp_path / "b"))
    corners, material = _all_corners(soup)
    assert np.all(np.isfinite(corners))
    mats = soup.header.materials
    assert material.min() >= 0 and material.max() < len(mats.kind)
    assert np.any(mats.kind[material] == GLASS)
    lights = corners[material == generate.LIGHT_ID]
    assert np.allclose(_normals(lights), [0.0, -1.0, 0.0])
    # Every light is LIGHT_DROP below the ceiling of its storey.
    ceilings = (np.floor(lights[:, 0, 1] / generate.ROOM_H) + 1) * generate.ROOM_H - generate.WALL / 2
    assert np.allclose(lights[:, :, 1], (ceilings - generate.LIGHT_DROP)[:, None], atol=1e-5)
    # The header's light table is exactly the light triangles written.
    table = soup.header.lights
    assert np.array_equal(table.p0, lights[:, 0].astype(np.float64))
    assert np.array_equal(soup.header.bounds, np.stack([corners.min((0, 1)), corners.max((0, 1))]))


def _edges_pair_up(corners):
    """Each directed edge (by exact corner bits) meets its reverse exactly once."""
    key = np.ascontiguousarray(corners).view(np.dtype((np.void, 12))).reshape(-1, 3)
    forward = np.stack([key, np.roll(key, -1, axis=1)], -1).reshape(-1, 2)
    as_rows = lambda e: np.ascontiguousarray(e).view(np.dtype((np.void, 24))).ravel()  # noqa: E731
    fwd, bwd = np.sort(as_rows(forward)), np.sort(as_rows(forward[:, ::-1]))
    return len(np.unique(fwd)) == len(fwd) and np.array_equal(fwd, bwd)


def _signed_volume(corners):
    c = np.asarray(corners, np.float64)
    return float(np.einsum("ij,ij->i", c[:, 0], np.cross(c[:, 1], c[:, 2])).sum() / 6)


def test_single_room_is_closed_and_objects_face_out():
    """Without doors every surface but the one-sided lights belongs to a
    closed mesh, including knots emitted in several slices (more than SLICE
    triangles); the shell faces in, furniture and glass face out."""
    blocks = []
    plan = plan_building(BuildingSpec(triangles=400_000, lights=4, rooms=(1, 1), floors=1, seed=3))
    room = plan.rooms[0]
    assert max(g.triangle_count() for g in room.glass) > generate.SLICE
    generate.emit_building(plan, lambda c, m: blocks.append((c, m)))
    corners = np.concatenate([c for c, _ in blocks])
    material = np.concatenate([m for _, m in blocks])
    assert _edges_pair_up(corners[material != generate.LIGHT_ID])
    shell = np.isin(material, [generate.WALL_ID, generate.FLOOR_ID, generate.CEILING_ID])
    assert _signed_volume(corners[shell]) == pytest.approx(-np.prod(room.hi - room.lo), rel=1e-5)
    furniture = np.isin(material, generate.CABINET_IDS + generate.TABLE_IDS)
    boxes = sum(np.prod(hi - lo) for lo, hi, _ in room.boxes)
    assert _signed_volume(corners[furniture]) == pytest.approx(boxes, rel=1e-4)
    # Each glass object on its own (they stand apart): closed, facing out.
    glass = corners[np.isin(material, generate.GLASS_IDS)]
    centre = glass.mean(axis=1)
    for obj in room.glass:
        reach = obj.size * (1.0 if obj.kind == "sphere" else generate._knot_reach())
        mine = np.hypot(centre[:, 0] - obj.centre_xz[0], centre[:, 2] - obj.centre_xz[1]) <= reach
        assert np.count_nonzero(mine) == obj.triangle_count()
        assert _edges_pair_up(glass[mine]) and _signed_volume(glass[mine]) > 0


def test_no_ray_leaves_the_free_space():
    """Rays from high in every room and from every door centre first hit a
    surface facing them: none slips into a wall, slab or the outside."""
    kw = dict(triangles=60_000, lights=12, rooms=(2, 3), floors=2)
    scene, plan = building_scene(**kw), plan_building(BuildingSpec(**kw))
    rng = np.random.default_rng(1)
    points = []
    for room in plan.rooms:
        high = rng.uniform(room.lo + 0.05, room.hi - 0.05, (400, 3))
        high[:, 1] = room.lo[1] + 2.5      # above furniture and glass, below the lights
        points.append(high)
        for d in room.doors:
            a, t = d.axis, 2 - d.axis
            p = np.empty((200, 3))
            p[:, a] = (room.hi[a] if d.sign > 0 else room.lo[a]) + d.sign * generate.WALL / 4
            p[:, t] = (d.d0 + d.d1) / 2
            p[:, 1] = room.lo[1] + generate.DOOR_H / 2
            points.append(p)
    origin = np.concatenate(points)
    direction = rng.normal(size=origin.shape)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    accel = Accelerator(scene.vertices, scene.triangles)
    hit, _, _, _ = accel.intersect(origin, direction)
    accel.close()
    assert np.all(hit != MISS)
    normal = _normals(scene.vertices[scene.triangles[hit]])
    assert np.all(np.einsum("ij,ij->i", normal, direction) < 0)


def _free_space(plan):
    """Boxes of the space rays may travel: room interiors and door openings."""
    boxes = [(r.lo, r.hi) for r in plan.rooms]
    for r in plan.rooms:
        for d in r.doors:
            a, t = d.axis, 2 - d.axis
            lo, hi = r.lo.copy(), r.hi.copy()
            wall = r.hi[a] if d.sign > 0 else r.lo[a]
            lo[a], hi[a] = sorted((wall, wall + d.sign * generate.WALL / 2))
            lo[t], hi[t], hi[1] = d.d0, d.d1, r.lo[1] + generate.DOOR_H
            boxes.append((lo, hi))
    return np.array([b[0] for b in boxes]), np.array([b[1] for b in boxes])


def test_walls_floors_and_ceilings_face_into_the_rooms():
    kw = dict(triangles=50_000, lights=12, rooms=(2, 3), floors=2)
    scene, plan = building_scene(**kw), plan_building(BuildingSpec(**kw))
    names = scene.materials.names
    shell = np.isin(scene.tri_material, [names.index(n) for n in ("wall", "floor", "ceiling")])
    corners = scene.vertices[scene.triangles[shell]].astype(np.float64)
    centre, normal = corners.mean(axis=1), _normals(corners)
    lo, hi = _free_space(plan)
    inside = lambda p: np.any(np.all((p[:, None] > lo) & (p[:, None] < hi), axis=2), axis=1)  # noqa: E731
    assert np.all(inside(centre + 0.01 * normal))
    assert not np.any(inside(centre - 0.01 * normal))


def test_every_interior_wall_has_an_open_door():
    kw = dict(triangles=60_000, lights=12, rooms=(2, 3), floors=2)
    scene, plan = building_scene(**kw), plan_building(BuildingSpec(**kw))
    origins, directions, lengths, walls = [], [], [], []
    for room in plan.rooms:
        for d in (d for d in room.doors if d.sign > 0):   # each wall once
            a, t = d.axis, 2 - d.axis
            o = np.empty(3)
            o[a], o[t], o[1] = room.hi[a] - 0.5, (d.d0 + d.d1) / 2, room.lo[1] + generate.DOOR_H / 2
            direction = np.zeros(3)
            direction[a] = 1.0
            origins.append(o)
            directions.append(direction)
            lengths.append(1.0 + generate.WALL)
            # The same ray moved along the wall, past the door: through the wall.
            w = o.copy()
            w[t] = d.d1 + 0.3 if d.d1 + 0.3 < room.hi[t] else d.d0 - 0.3
            walls.append(w)
    assert len(origins) == 2 * (2 * 2 + 1 * 3)   # per floor: 2 rows x 2 x-walls, 1 x 3 z-walls
    accel = Accelerator(scene.vertices, scene.triangles)
    d, tmax = np.array(directions), np.array(lengths)
    through_door, _, _, _ = accel.intersect(np.array(origins), d, tmax)
    through_wall, _, _, _ = accel.intersect(np.array(walls), d, tmax)
    accel.close()
    assert np.all(through_door == MISS)
    assert np.all(through_wall != MISS)


def test_small_building_renders():
    from dosppm_core.modes.sppm import Renderer
    from dosppm_core.settings import RenderSettings
    scene = building_scene(triangles=200_000, lights=24)
    assert abs(scene.triangle_count - 200_000) <= 20_000 and len(scene.lights.kind) == 48
    renderer = Renderer(scene, RenderSettings(photons_per_iteration=20_000))
    try:
        progress = renderer.run_iteration()
        image = renderer.image()
    finally:
        renderer.close()
    assert np.all(np.isfinite(image)) and image.mean() > 0
    assert progress.path_ends["escaped"] == 0      # the building is closed


def test_too_few_triangles_and_bad_parameters_are_scene_errors():
    with pytest.raises(SceneError, match="too few for 4 rooms.*need at least"):
        plan_building(BuildingSpec(triangles=1_000, lights=8, rooms=(2, 2), floors=1))
    with pytest.raises(SceneError, match="lights"):
        plan_building(BuildingSpec(triangles=100_000, lights=0))
    assert scenes_cli.parse_count("20M") == 20_000_000
    assert scenes_cli.parse_count("100k") == 100_000 and scenes_cli.parse_count("1.5M") == 1_500_000
    assert scenes_cli.parse_count("250_000") == 250_000
    for bad in ("", "x", "12x", "-5", "0", "0.5", "1e400", "nan"):
        with pytest.raises(SceneError, match="--triangles"):
            scenes_cli.parse_count(bad)
    assert scenes_cli.parse_rooms("8x6") == (8, 6)
    with pytest.raises(SceneError, match="--rooms"):
        scenes_cli.parse_rooms("8by6")


_RSS_SCRIPT = """
import json, resource, sys
from dosppm_core.scene.generate import generate_building
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
report = generate_building(sys.argv[1], triangles=3_000_000, lights=200)
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"growth_kib": after - before, "bytes": report.bytes, "triangles": report.triangles,
                  "seconds": report.seconds}))
"""


def test_generation_streams_in_bounded_memory(tmp_path):
    """Peak RSS grows by a small fraction of the soup: blocks, not the scene
    (measured: about 19 MB for a 120 MB soup of 3M triangles)."""
    import json
    out = run_python("-c", _RSS_SCRIPT, tmp_path / "b", timeout=120)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert result["triangles"] >= 2_700_000
    assert result["growth_kib"] * 1024 < 0.4 * result["bytes"], result


def test_cli_generates_and_rejects_bad_counts(tmp_path):
    out = run_dosppm("scenes", "generate", "building", "--triangles", "100k", "--lights", "12",
                     "--out", tmp_path / "b", timeout=120)
    assert out.returncode == 0, out.stderr
    assert "triangles" in out.stdout and "12 lights" in out.stdout and "bytes" in out.stdout
    assert open_soup(str(tmp_path / "b")).count == pytest.approx(100_000, rel=0.1)
    bad = run_dosppm("scenes", "generate", "building", "--triangles", "lots", "--out", tmp_path / "c",
                     timeout=120)
    assert bad.returncode == 2
    assert bad.stderr.strip().count("\n") == 0 and "--triangles" in bad.stderr
    listing = run_dosppm("scenes", timeout=120)
    assert listing.returncode == 0 and "cornell-box" in listing.stdout
