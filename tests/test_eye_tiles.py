"""Tracers make their own eye rays (issue 32): the server sends an eye
iteration's tiles as (job id, pixel start, count) to the tracer serving
the chunk each tile's rays start in, which makes the rays with the
library's call and sends them on as it sends the photons it makes
(services/tracer/state.py `TracerState.eye_tiles`).

- The rays are bit for bit those the server made and sent before, in the
  same packages per start chunk; those that miss the scene end escaped,
  in the tracer's results, which return the credit its packages do not
  carry.
- Each tile goes to a tracer of the chunk its rays start in (any camera:
  an orthographic one's tiles start in several chunks, or miss the
  scene); a tracer serving none of them forwards every ray, and every eye
  job still completes exactly once, as the ledger's re-trace confirms.
- A tile outside the image is refused whole, with one line.
"""
from __future__ import annotations

import dataclasses
from fractions import Fraction

import numpy as np

import dosppm_core as dp

from dosppm_core.chunks.view import start_chunks
from dosppm_core.jobs import ESCAPED, RayBatch
from dosppm_core.trace import environment, escaped_light, eye_ray_job
from services import ledger, wire
from services.inproc import InProcessCluster
from services.server.balance import tile_chunks
from services.tracer.state import SERVER, TracerState
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
from tests.helpers.cluster import caustic_scene, settings
from tests.helpers.credit import credit_sum


def _over_the_wire(msg_type: str, fields: dict):
    return wire.decode([bytes(f) for f in wire.encode(msg_type, **fields)])


def _server_made(provider, seed, iteration, ids, starts, counts):
    """What the server sent before this change for these tiles: each
    tile's `eye_ray_job` rays routed by start chunk, concatenated per chunk
    in tile order; and the count that missed the scene."""
    parts, lost = {}, 0
    for j, start, count in zip(ids.tolist(), starts.tolist(), counts.tolist()):
        batch = eye_ray_job(provider.header, seed, iteration, start, count)
        batch.job[:] = j
        routed, missed = start_chunks(provider.tree, batch)
        lost += missed
        for k, part in routed.items():
            parts.setdefault(k, []).append(part)
    return {k: RayBatch.concat(p) for k, p in parts.items()}, lost


def _cut_provider():
    """The caustic scene in two chunks (lower and upper half) of a box cut
    below the light: the upper rows' rays start in chunk 1, the lower
    rows' in chunk 0, and some pass over the cut box and miss it."""
    scene = caustic_scene()
    box = root_box(scene)
    box[1, 1] = 400.0
    return MemoryChunks(scene, uniform_tree(box, (1, 2, 1)))


def test_a_tracer_makes_bit_for_bit_the_eye_rays_the_server_sent_and_returns_the_rest_of_the_credit():
    provider = _cut_provider()
    a = TracerState("inproc://a", provider, 10, seed=7)
    try:
        a.set_peers(1, [["inproc://a"], ["inproc://b"]])
        ids, starts = np.array([40, 41, 42], np.int64), np.array([0, 1500, 3000], np.int64)
        counts = np.array([1000, 1200, 1096], np.int64)        # the last ends at pixel 64 * 64
        msg = _over_the_wire("eye_job", dict(eye_iteration=3, job_ids=ids, pixel_starts=starts, counts=counts,
                                             credit_job=ids, credit_exp=np.zeros(3, np.int64)))
        out = a.handle(msg)
        queued = [(kind, e, p) for kind, e, p in a.schedule.pop(0).items()]
    finally:
        a.close()
    want, lost = _server_made(provider, 7, 3, ids, starts, counts)
    assert set(want) == {0, 1} and 0 < lost < counts.sum() // 2
    results = [o.fields for o in out if o.type == "results"]
    portal = [o for o in out if o.type == "portal_rays"]
    assert len(results) == 1 and [o.dest for o in portal] == ["inproc://b"]
    assert {(kind, e) for kind, e, _ in queued} == {("eye", 3)}
    assert portal[0].fields["kind"] == "eye" and portal[0].fields["eye_iteration"] == 3
    got = {0: RayBatch.concat([p.batch for _, _, p in queued]), 1: portal[0].fields["batch"]}
    for k in (0, 1):
        for col, column in want[k].arrays().items():
            assert getattr(got[k], col).tobytes() == column.tobytes(), (k, col)
    # The emission's results: every ray fed, those in a chunk went on, the
    # others escaped; no hit points. And the credit is all there, once.
    r = _over_the_wire("results", results[0])
    assert r.chunk is None and r.eye_iteration == 3 and not len(r.hits) and r.deposits is None
    assert not len(r.emitted_pixels)                        # no environment to see
    assert r.job_ids.tolist() == ids.tolist() and r.job_fed.tolist() == counts.tolist()
    assert int((r.job_fed - r.job_left).sum()) == lost == int(r.ends[ESCAPED]) == int(r.ends.sum())
    forwarded = (portal[0].fields["credit_job"], portal[0].fields["credit_exp"])
    total = credit_sum([(r.credit_job, r.credit_exp), forwarded, *[p.credit for _, _, p in queued]])
    assert total == {j: Fraction(1) for j in ids.tolist()}
    assert a.counters["eye_rays_made"] == counts.sum()


def test_a_tile_outside_the_image_is_refused_whole_with_one_line():
    provider = _cut_provider()
    a = TracerState("inproc://a", provider, 10, seed=7)
    no_seed = TracerState("inproc://n", provider, 10)
    try:
        a.set_peers(1, [["inproc://a"], ["inproc://b"]])
        ids = np.array([1, 2], np.int64)
        msg = _over_the_wire("eye_job", dict(eye_iteration=0, job_ids=ids, pixel_starts=np.array([0, 4000]),
                                             counts=np.array([10, 97]), credit_job=ids,
                                             credit_exp=np.zeros(2, np.int64)))
        out = a.handle(msg)
        assert [(o.dest, o.type) for o in out] == [(SERVER, "error")]
        reason = out[0].fields["reason"]
        assert reason.startswith("eye_job: ") and "4097" in reason and "4096" in reason and "\n" not in reason
        assert not a.has_work() and a.counters["eye_rays_made"] == 0
        msg = _over_the_wire("eye_job", dict(eye_iteration=0, job_ids=ids[:1], pixel_starts=np.array([0]),
                                             counts=np.array([10]), credit_job=ids[:1],
                                             credit_exp=np.zeros(1, np.int64)))
        out = no_seed.handle(msg)
        assert [o.type for o in out] == ["error"] and "seed" in out[0].fields["reason"]
    finally:
        a.close()
        no_seed.close()


def test_the_eye_rays_are_made_with_the_renders_camera_not_the_stores():
    """`dosppm render --width 64` renders a store whose header keeps the
    scene's own resolution: the tracer makes the rays with the camera the
    server's welcome sends (the node passes it as `header`)."""
    provider = _cut_provider()
    cam = provider.header.camera
    header = dataclasses.replace(provider.header, camera=dataclasses.replace(cam, width=32, height=24))
    t = TracerState("inproc://a", provider, 10, seed=7, header=header)
    try:
        t.set_peers(1, [["inproc://a"], ["inproc://a"]])
        one = np.ones(1, np.int64)
        out = t.eye_tiles(0, one, np.array([0]), np.array([32 * 24]), (one, 0 * one))
        queued = [p.batch for k in (0, 1) if k in t.schedule.queues for _, _, p in t.schedule.pop(k).items()]
        past = dict(eye_iteration=0, job_ids=one, pixel_starts=np.array([0]), counts=np.array([32 * 24 + 1]),
                    credit_job=one, credit_exp=0 * one)
        refused = t.handle(_over_the_wire("eye_job", past))
    finally:
        t.close()
    made = RayBatch.concat(queued)
    want = eye_ray_job(header, 7, 0, 0, 32 * 24)
    assert int(out[0].fields["ends"][ESCAPED]) + len(made) == 32 * 24
    order = np.argsort(made.pixel, kind="stable")
    rows = made.pixel[order]
    assert np.array_equal(made.direction[order], want.direction[rows])
    assert not np.array_equal(want.direction, eye_ray_job(provider.header, 7, 0, 0, 32 * 24).direction)
    assert [o.type for o in refused] == ["error"] and "768" in refused[0].fields["reason"]


def _sky_scene(tmp_path):
    """A diffuse sphere under a constant sky: the rays around it miss the
    scene's box and see the sky."""
    path = tmp_path / "sky.xml"
    path.write_text("""<scene version="3.0.0">
        <emitter type="constant"><rgb name="radiance" value="0.8, 0.9, 1.0"/></emitter>
        <sensor type="perspective"><float name="fov" value="35"/>
            <transform name="to_world"><lookat origin="0, 0.3, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
            <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/></film>
        </sensor>
        <shape type="sphere"><float name="radius" value="0.8"/>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>
    </scene>""")
    return dp.load(str(path))


def test_eye_rays_missing_the_scene_bring_the_sky_in_the_tracers_results(tmp_path):
    """What the server added itself before: the environment the rays
    missing the scene see, per pixel, now in the results of the tracer
    that made them (the library's `escaped_light` of those rays)."""
    scene = _sky_scene(tmp_path)
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (1, 1, 1)))
    t = TracerState("inproc://a", provider, 10, seed=3)
    try:
        t.set_peers(1, [["inproc://a"]])
        ids = np.array([7, 8], np.int64)
        out = t.eye_tiles(2, ids, np.array([0, 512]), np.array([512, 512]), (ids, 0 * ids))
    finally:
        t.close()
    r = _over_the_wire("results", out[0].fields)
    rays = RayBatch.concat([eye_ray_job(provider.header, 3, 2, s, 512) for s in (0, 512)])
    _routed, lost = start_chunks(provider.tree, rays, keep_lost=True)
    pixels, rgb = escaped_light(environment(scene.lights), lost)
    assert r.eye_iteration == 2 and 0 < len(lost) == int(r.ends[ESCAPED]) < 1024
    assert r.emitted_pixels.tolist() == pixels.tolist() and np.array_equal(r.emitted_rgb, rgb)
    assert (rgb > 0.5).all()


def _eye_jobs_sent(c, monkeypatch) -> tuple[list, list]:
    """Watch the cluster: (eye job ids sent, eye jobs completed), in order."""
    sent, completed = [], []
    complete, post = c.server._complete, c._post
    monkeypatch.setattr(c.server, "_complete",
                        lambda j, job: (job.kind == "eye" and completed.append(j), complete(j, job)))

    def watch(sender, outs):
        outs = list(outs)
        sent.extend((o.dest, j) for o in outs if o.type == "eye_job" for j in o.fields["job_ids"].tolist())
        post(sender, outs)
    monkeypatch.setattr(c, "_post", watch)
    return sent, completed


def _assert_exact(c, provider, sent, completed) -> None:
    k = c.server.counters
    ids = [j for _, j in sent]
    assert sorted(completed) == sorted(ids) and len(set(ids)) == len(ids)
    assert k["eye_jobs_completed"] == len(ids) and k["over_credited_jobs"] == 0
    assert k["photons_emitted"] == k["photons_completed"] == k["photons_committed"] == k["photon_paths_ended"]
    assert k["stale_paths"] == 0 and k["deposits_late"] == 0 and not c.server.jobs
    assert ledger.check(provider, c.statistics.ledger.records) == []


def _front_and_back(tile_chunk: int | None = None) -> InProcessCluster:
    """2 tracers on the caustic scene cut into front (chunk 0, t0's: every
    camera ray starts there) and back (chunk 1, t1's); `tile_chunk`: the
    chunk every tile is sent for instead of its own."""
    scene = caustic_scene()
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (1, 1, 2)))
    c = InProcessCluster(provider, dataclasses.replace(settings(5), photon_batch=20_000), tracers=2)
    assert set(c.server.tile_chunks) == {0} and c.server.owners == [["t0"], ["t1"]]
    if tile_chunk is not None:
        c.server.tile_chunks = [tile_chunk] * len(c.server.tile_chunks)
    return c


def test_a_tracer_serving_none_of_the_cameras_chunks_forwards_every_eye_ray_and_each_eye_job_completes_once(
        monkeypatch):
    """Every tile is sent to t1, which serves none of the chunks the
    camera's rays start in: it makes every eye ray and passes each on to
    t0. Every eye job completes once, and the image is bit for bit the one
    made when t0 makes the rays (the same rays, in the same packages)."""
    images = []
    for tile_chunk in (1, None):
        c = _front_and_back(tile_chunk)
        sent, completed = _eye_jobs_sent(c, monkeypatch)
        try:
            c.run(photons=90_000)
        finally:
            c.close()
        made = {tid: t.counters["eye_rays_made"] for tid, t in c.tracers.items()}
        maker = "t1" if tile_chunk == 1 else "t0"
        assert {dest for dest, _ in sent} == {maker} and sum(made.values()) == made[maker]
        assert made[maker] == c.server.eye_started * c.server.n_pixels and c.server.eye_completed >= 2
        if maker == "t1":
            assert c.tracers["t1"].counters["portal_rays_out"] >= made["t1"]
        _assert_exact(c, c.store, sent, completed)
        images.append(np.asarray(c.image()))
    assert images[0].tobytes() == images[1].tobytes()


def test_an_orthographic_cameras_tiles_go_to_the_chunks_they_start_in_and_tiles_missing_the_scene_complete():
    """An orthographic camera wider and taller than the scene: its top and
    bottom tiles miss the scene (-1), the upper rows start in chunk 1, the
    lower in chunk 0. Each tile goes to that chunk's tracer; those that
    miss end escaped at a tracer and still complete their iteration."""
    scene = caustic_scene()
    cam = dataclasses.replace(scene.camera, projection="orthographic", ortho_scale=(400.0, 400.0))
    scene = dataclasses.replace(scene, camera=cam)
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (1, 2, 1)))
    s = dataclasses.replace(settings(5), photon_batch=20_000, tile_pixels=256)
    tiles = tile_chunks(provider.header, provider.tree, 5, 256)
    assert tiles[:2] == [-1, -1] and tiles[-2:] == [-1, -1] and tiles[2] == 1 and tiles[-3] == 0
    inner = tiles[2:-2]
    assert inner == sorted(inner, reverse=True) and set(inner) == {0, 1}
    c = InProcessCluster(provider, s, tracers=2)
    assert c.server.tile_chunks == tiles and c.server.owners == [["t0"], ["t1"]]
    sent = []
    post = c._post

    def watch(sender, outs):
        outs = list(outs)
        sent.extend((o.dest, o.fields["eye_iteration"], start) for o in outs if o.type == "eye_job"
                    for start in o.fields["pixel_starts"].tolist())
        post(sender, outs)
    c._post = watch
    try:
        c.run(photons=90_000)
    finally:
        c.close()
    first = {start // 256: dest for dest, e, start in sent if e == 0}
    assert sorted(first) == list(range(len(tiles)))
    assert all(first[i] == f"t{k}" for i, k in enumerate(tiles) if k >= 0)
    k = c.server.counters
    assert c.server.eye_completed >= 2 and k["eye_jobs_completed"] == len(sent) and not c.server.jobs
    assert c.server.path_ends[ESCAPED] >= 4 * 256 * c.server.eye_completed     # the tiles that miss
    assert ledger.check(provider, c.statistics.ledger.records) == []
