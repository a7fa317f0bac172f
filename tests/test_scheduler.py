"""The server's state machine alone, fed hand-made messages: chunk
assignment, the peer table, exact accounting and back-pressure."""
from __future__ import annotations

import numpy as np
import pytest

from dosppm_core.jobs import PhotonDeposits
from dosppm_core.settings import RenderSettings
from services import wire
from services.server import checkpoint
from services.server.held import DEPOSIT_BYTES, DISCARDED, HeldDeposits
from services.server.balance import assign_chunks
from services.server.options import ServerOptions
from services.server.state import ServerState
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
from tests.helpers.scenes import small_scene


def _msg(msg_type, **fields):
    return wire.decode([bytes(f) for f in wire.encode(msg_type, **fields)])


def _register(state, tid, now=0.0):
    return state.on_register(tid, _msg("register", tracer_id=tid, capacity={"cores": 1, "memory_bytes": 0},
                                       endpoint=f"tcp://{tid}:1", has_store=True, store_key="k"), now)


def new_state(cells=(2, 2, 1), photons_per_job=512):
    """A server state for the small Cornell box in `cells` chunks."""
    scene = small_scene("cornell-box", 32)
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), cells))
    return ServerState(provider.header, provider.tree,
                       RenderSettings(photons_per_job=photons_per_job, tile_pixels=256,
                                      photons_per_iteration=10_000),
                       "k", options=ServerOptions(min_photon_jobs=50, queue_target_rays=4096))


@pytest.fixture()
def state():
    return new_state()


@pytest.mark.parametrize("c, n, expected", [
    (4, 2, [["a"], ["b"], ["a"], ["b"]]),
    (2, 2, [["a"], ["b"]]),
    (1, 3, [["a", "b", "c"]]),
    (2, 3, [["a", "c"], ["b"]]),
    (3, 0, [[], [], []]),
])
def test_round_robin_assignment(c, n, expected):
    assert assign_chunks(c, ["a", "b", "c"][:n]) == expected


def test_every_tracer_gets_the_new_table_when_one_joins(state):
    out = _register(state, "a")
    assert [o.type for o in out] == ["welcome", "peers"]
    assert out[0].fields["chunks"] == [0, 1, 2, 3] and out[0].fields["manifest"] is None
    out = _register(state, "b")
    peers = [o for o in out if o.type == "peers"]
    assert {o.dest for o in peers} == {"a", "b"}
    assert all(o.fields["table_version"] == 2 for o in peers)
    assert peers[0].fields["peers"] == [["tcp://a:1"], ["tcp://b:1"], ["tcp://a:1"], ["tcp://b:1"]]
    # A rejoin under the same id keeps the tracer's place.
    out = _register(state, "a")
    assert out[0].fields["tracer_index"] == 0 and state.table_version == 2


def test_unregistered_sender_gets_an_error(state):
    out = state.on_message("ghost", _msg("heartbeat"), 0.0)
    assert out[0].type == "error" and "not registered" in out[0].fields["reason"]


def _results(job_ids, job_ended, deposits_job=(), credit=()):
    """Paths of each job fed into a step and ended there (none left), and
    the credit it returns: [(job, exponent)]."""
    ended = int(np.sum(job_ended))
    dep = PhotonDeposits(*(np.zeros((len(deposits_job), 3), np.float32) for _ in range(3)),
                         job=np.asarray(deposits_job, np.int64))
    return _msg("results", chunk=0, ends=np.array([0, ended, 0, 0, 0], np.int64),
                job_ids=np.asarray(job_ids, np.int64), job_fed=np.asarray(job_ended, np.int64),
                job_left=np.zeros(len(job_ids), np.int64),
                credit_job=np.array([j for j, _ in credit], np.int64),
                credit_exp=np.array([e for _, e in credit], np.int64), deposits=dep)


def _rays(o) -> int:
    """Rays a job message has the tracer make: its photon jobs' or tiles' counts."""
    return int(o.fields["counts"].sum())


def _shares(out, j):
    """The credit terms of job j its job messages carried."""
    return [(j, e) for o in out if o.type in ("photon_job", "eye_job")
            for jj, e in zip(o.fields["credit_job"].tolist(), o.fields["credit_exp"].tolist()) if jj == j]


def test_a_job_counts_once_when_all_its_paths_have_ended(state):
    _register(state, "a")
    state.cull_box = np.array([[-1e9] * 3, [1e9] * 3])
    state.eye_completed = 1                       # hit points exist
    out = state.tick(0.0)
    j = next(j for j, job in state.jobs.items() if job.kind == "photon")
    paths, shares = state.jobs[j].paths, _shares(out, j)
    # Half of the first share back: all paths ended, but credit is missing
    # (a message still on its way could hold deposits).
    half = [(j, shares[0][1] + 1)]
    state.on_message("a", _results([j], [paths - 1], deposits_job=[j, j], credit=half), 0.1)
    assert j in state.jobs and state.counters["photons_completed"] == 0
    state.on_message("a", _results([j], [1], credit=half + shares[1:]), 0.2)
    assert j not in state.jobs and state.counters["photons_completed"] == paths
    # Late or duplicated reports of a finished job are stale, never counted.
    state.on_message("a", _results([j], [5], credit=half), 0.3)
    assert state.counters["stale_paths"] == 5 and state.counters["photons_completed"] == paths
    state.stop_emitting()
    state.jobs.clear()
    state.finish()
    photons = [u for u in state.updates if u.kind == "photons"]
    assert sum(u.photons_emitted for u in photons) == paths
    assert sum(len(p) for u in photons for p in u.deposits) == 2


def test_deposits_of_unfinished_jobs_wait_for_their_job(state):
    _register(state, "a")
    state.cull_box = np.array([[-1e9] * 3, [1e9] * 3])
    state.eye_completed = 1
    state.settings.photon_batch = 3
    state.held = HeldDeposits(3, 1 << 30)
    out = state.tick(0.0)
    j1, j2 = [j for j, job in state.jobs.items() if job.kind == "photon"][:2]
    state.on_message("a", _results([j1], [512], deposits_job=[j1, j2, j2], credit=_shares(out, j1)), 0.1)
    u = [u for u in state.updates if u.kind == "photons"]
    assert len(u) == 1 and PhotonDeposits.concat(u[0].deposits).job.tolist() == [j1]
    assert u[0].photons_emitted == 512


def test_photons_that_deposit_nothing_commit_once_a_batch_of_them_is_complete(state):
    """Direct light only (a Mitsuba max_depth 2 scene): no photon deposits,
    yet a photon or iteration limit waits for committed photons."""
    _register(state, "a")
    state.cull_box = np.array([[-1e9] * 3, [1e9] * 3])
    state.eye_completed = 1
    state.settings.photon_batch = 1024
    state.held = HeldDeposits(1024, 1 << 30)
    out = state.tick(0.0)
    j1, j2 = [j for j, job in state.jobs.items() if job.kind == "photon"][:2]
    state.on_message("a", _results([j1], [512], credit=_shares(out, j1)), 0.1)
    assert state.counters["photons_committed"] == 0          # half a batch: held back
    state.on_message("a", _results([j2], [512], credit=_shares(out, j2)), 0.2)
    assert state.counters["photons_committed"] == 1024


def test_a_tracer_that_does_not_report_gets_no_more_than_its_queue_allowance(state):
    _register(state, "a")
    state.cull_box = np.array([[-1e9] * 3, [1e9] * 3])
    state.eye_completed = 1
    sent = {"photon_job": 0, "eye_job": 0}
    for i in range(20):
        for o in state.tick(i * 0.1):
            if o.type in sent:
                sent[o.type] += _rays(o)
    # Eye tiles are not held back (hit points gate everything); photons
    # stop at the queue allowance, overshooting by at most one job, and nothing
    # more goes out without a report.
    assert sent["eye_job"] == 32 * 32            # every pixel's ray, made at the tracer
    assert 4096 <= sum(sent.values()) <= 4096 + 512
    assert state.photon_jobs_in_flight >= state.min_photon_jobs


def _photons_sent(out) -> int:
    return sum(_rays(o) for o in out if o.type == "photon_job")


@pytest.mark.parametrize("limit_rows, full", [(10, True), (1 << 20, False)])
def test_held_deposits_past_their_memory_stop_photon_jobs_until_a_job_completes(limit_rows, full):
    """Issue 17: deposits wait at the server until their job completes, and
    the tracers' queues decide how many jobs are in flight. Past its
    --queue-memory the server sends no photon job; once the job completes,
    a batch hands its deposits over and photon jobs go out again. The
    control, with room, goes on sending."""
    state = new_state()
    state.held = HeldDeposits(1 << 20, limit_rows * DEPOSIT_BYTES)
    _register(state, "a")
    state.cull_box = np.array([[-1e9] * 3, [1e9] * 3])
    state.eye_completed = 1
    out = state.tick(0.0)
    j = next(j for j, job in state.jobs.items() if job.kind == "photon")
    state.on_message("a", _results([j], [1], deposits_job=[j] * 10), 0.1)    # no credit back: in flight
    assert state.held.full == full
    assert (_photons_sent(state.tick(0.2)) == 0) == full
    if full:
        state.on_message("a", _results([j], [state.jobs[j].paths - 1], credit=_shares(out, j)), 0.3)
        assert not state.held.full
        assert [len(p) for u in state.updates if u.kind == "photons" for p in u.deposits] == [10]
        assert _photons_sent(state.tick(0.4)) > 0


def test_photon_jobs_in_flight_are_as_many_as_their_held_deposits_fit():
    """Out of core a job completes only when its last path ends, sweeps
    later, so the server holds every deposit of every job in flight. It
    makes no more jobs than its --queue-memory holds (less a batch, half
    at most), at the deposits
    per photon path ended so far (4 guessed before any end); the control
    with room keeps the paper's minimum in flight (50 here)."""
    state, roomy = new_state(), new_state()
    state.held = HeldDeposits(1 << 20, 40 * 512 * DEPOSIT_BYTES)
    for s in (state, roomy):
        _register(s, "a")
        s.cull_box = np.array([[-1e9] * 3, [1e9] * 3])
        s.eye_completed = 1
        s.tick(0.0)
    assert roomy.photon_jobs_in_flight == 50
    assert state.photon_jobs_in_flight == 40 * 512 // 2 // (512 * 4)
    j = next(j for j, job in state.jobs.items() if job.kind == "photon")
    # Every path of one job ends, with a deposit each (its credit not back yet).
    state.on_message("a", _results([j], [512], deposits_job=[j] * 512), 0.1)
    state.tick(0.2)
    assert state.photon_jobs_in_flight == 40 * 512 // 2 // 512


def test_no_photons_before_the_first_hit_points(state):
    _register(state, "a")
    out = state.tick(0.0)
    assert {o.type for o in out} <= {"heartbeat", "eye_job"}
    assert any(o.type == "eye_job" for o in out)


def test_eviction_re_emits_the_same_photons_under_new_job_ids(state):
    _register(state, "a")
    _register(state, "b")
    state.cull_box = np.array([[-1e9] * 3, [1e9] * 3])
    state.eye_completed = 1
    first = {}                 # rng key -> photons, of the jobs sent
    for o in state.tick(0.0):
        if o.type == "photon_job":
            first.update(zip(o.fields["rng_keys"].tolist(), o.fields["counts"].tolist()))
    sent = dict(state.jobs)
    out = state.evict("b", "test")
    assert {o.type for o in out} == {"peers"} and state.owners == [["a"]] * 4
    gone = [j for j, job in sent.items() if job.sent]
    assert gone and not set(gone) & set(state.jobs)
    # Their late deposits are stale: the status the results handler consults.
    photon = np.array([j for j in gone if sent[j].kind == "photon"], np.int64)
    assert len(photon) and np.all(state._job_status(photon) == DISCARDED)
    again = {}
    for o in state.tick(1.0):
        if o.type == "photon_job":
            assert not set(o.fields["job_ids"].tolist()) & set(sent), "a job id was reused"
            again.update(zip(o.fields["rng_keys"].tolist(), o.fields["counts"].tolist()))
    common = set(first) & set(again)
    assert common, "no re-emitted job was sent"
    # The same random streams and counts, whatever new id carries them: the
    # same photons (the tracer makes them from these: tests/test_emission.py).
    assert all(first[key] == again[key] for key in common)
    # Results of a discarded job are stale, and its deposits never count.
    old = next(j for j, job in sent.items() if job.kind == "photon" and job.rng_key in common)
    state.on_message("a", _results([old], [3], deposits_job=[old]), 1.1)
    assert state.counters["stale_paths"] == 3


def _beat(state, tid, now, **status):
    return state.on_message(tid, _msg("heartbeat", status=status), now)


def test_job_messages_an_idle_tracer_never_got_are_re_emitted_at_once(state, monkeypatch):
    """Job messages lost with a connection libzmq replaced: the tracer's
    heartbeats acknowledge fewer than were sent, it is idle, and the oldest
    unacknowledged one is JOB_MESSAGE_LOST_S old, so it is welcomed again
    (a new session) and the jobs in flight are re-emitted, long before the
    30 s watchdog. A busy tracer, or one that acknowledged everything, is
    left alone."""
    from services.server import eye_schedule
    from services.server.membership import JOB_MESSAGE_LOST_S
    monkeypatch.setattr(eye_schedule, "EYE_RAYS_PER_MESSAGE", 256)     # a message per tile: several sent
    _register(state, "a")
    state.cull_box = np.array([[-1e9] * 3, [1e9] * 3])
    state.eye_completed = 1
    sent = sum(o.type in ("photon_job", "eye_job") for o in state.tick(0.0))
    t = state.tracers["a"]
    assert sent > 2 and t.jobs_sent == sent
    in_flight = {j for j, job in state.jobs.items() if job.sent}
    session = t.session
    late = JOB_MESSAGE_LOST_S + 0.5
    # Too recent, or busy: nothing happens.
    assert _beat(state, "a", 1.0, session=session, jobs_received=sent - 2, queue=0) == []
    assert _beat(state, "a", late, session=session, jobs_received=sent - 2, queue=500) == []
    assert state.counters["job_messages_lost"] == 0 and in_flight <= set(state.jobs)
    # Idle, two unacknowledged for long enough: lost.
    out = _beat(state, "a", late, session=session, jobs_received=sent - 2, queue=0)
    assert [o.type for o in out][:1] == ["welcome"] and out[0].fields["settings"]["session"] == session + 1
    assert state.counters["job_messages_lost"] == 2
    assert not (set(state.jobs) & in_flight), "the jobs in flight were not discarded"
    assert t.jobs_sent == 0 and not t.unacked
    # Heartbeats of the old session do not count against the new one, and
    # in the new one everything acknowledged is never suspected.
    assert _beat(state, "a", late + 1.0, session=session, jobs_received=0, queue=0) == []
    resent = sum(o.type in ("photon_job", "eye_job") for o in state.tick(late + 1.0))
    assert resent > 0 and t.jobs_sent == resent
    assert _beat(state, "a", late + 60, session=session + 1, jobs_received=resent, queue=0) == []
    assert state.counters["job_messages_lost"] == 2


def test_jobs_untouched_while_every_tracer_is_idle_are_re_emitted_after_the_stall_time(state):
    """Portal packages lost between two tracers leave jobs in flight that no
    one works on. When every tracer's fresh heartbeat says it holds nothing
    (no queue, no outbox), a job untouched for STALL_S is lost; a busy
    tracer, or one whose heartbeat is stale (loading a chunk), defers to
    the 30 s watchdog."""
    from services.server.state import STALL_S
    _register(state, "a")
    _register(state, "b")
    state.cull_box = np.array([[-1e9] * 3, [1e9] * 3])
    state.eye_completed = 1
    state.tick(0.0)
    sent = {j for j, job in state.jobs.items() if job.sent}
    assert sent
    late = STALL_S + 1.0
    _beat(state, "a", late - 0.5, queue=0, outbox_rays=0)
    _beat(state, "b", late - 0.5, queue=120, outbox_rays=0)            # b is busy
    state.tick(late)
    assert state.counters["jobs_timed_out"] == 0 and sent <= set(state.jobs)
    _beat(state, "b", late + 1.5, queue=0, outbox_rays=0)
    state.tick(late + 2.5)                                                 # a's heartbeat is stale now
    assert state.counters["jobs_timed_out"] == 0 and sent <= set(state.jobs)
    _beat(state, "a", late + 3.0, queue=0, outbox_rays=0)
    _beat(state, "b", late + 3.0, queue=0, outbox_rays=0)
    state.tick(late + 3.5)
    assert state.counters["jobs_timed_out"] == 1
    assert not (sent & set(state.jobs)), "the stalled jobs were not discarded"


def _waiting_state(timeout_s):
    scene = small_scene("cornell-box", 32)
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 1, 1)))
    return ServerState(provider.header, provider.tree, RenderSettings(photons_per_job=512, tile_pixels=256),
                       "k", options=ServerOptions(min_photon_jobs=8, min_tracers=3, min_tracers_timeout_s=timeout_s,
                                                 tracer_timeout_s=1e6))     # no evictions: the wait is under test


def _jobs(outs):
    return [o for o in outs if o.type in wire.JOB_MESSAGES]


def test_the_server_says_what_it_waits_for_and_starts_with_all_tracers():
    s = _waiting_state(None)
    assert s.waiting_for() == {"tracers": 3, "registered": 0, "min_tracers": 3}
    _register(s, "a")
    _register(s, "b")
    assert not _jobs(s.tick(1000.0)) and not s.started       # no timeout: waits for ever
    assert s.status()["waiting_for"] == {"tracers": 1, "registered": 2, "min_tracers": 3}
    _register(s, "c")
    assert _jobs(s.tick(1001.0)) and s.started
    assert s.waiting_for() is None and s.start_note is None


def test_min_tracers_timeout_starts_with_the_tracers_there_are():
    early = _waiting_state(30.0)
    early.tick(0.0)
    _register(early, "a", now=10.0)
    assert not _jobs(early.tick(29.0)) and not early.started    # within the timeout: waits
    s = _waiting_state(30.0)
    s.tick(0.0)
    assert not _jobs(s.tick(40.0)) and not s.started          # none yet: nothing to render with
    _register(s, "a", now=41.0)
    assert _jobs(s.tick(41.0)) and s.started                  # one, and 30 s have passed
    assert s.start_note == "starting with 1 of 3 tracers: waited 30 s (--min-tracers-timeout)"
    assert s.waiting_for() is None


def test_a_chunk_left_without_a_tracer_is_what_the_render_waits_for(state):
    _register(state, "a")
    state.tick(0.0)
    assert state.waiting_for() is None
    state.owners[1] = []          # as after its only tracer was evicted
    assert state.waiting_for() == {"chunk_owners": [1]}


def test_a_resumed_server_never_takes_the_killed_servers_jobs_for_its_own(tmp_path):
    """The killed server made jobs after its last checkpoint, and the
    tracers go on sending their deposits and credit: under the resumed
    server's own block of ids they are stale, never its jobs'. (With the
    checkpoint's next_job as the first id, as before, they were taken for
    new jobs: CI's server-kill test saw 200 deposits arrive late.)"""
    killed = new_state()
    _register(killed, "a")
    killed.cull_box, killed.eye_completed = np.array([[-1e9] * 3, [1e9] * 3]), 1
    doc = dict(killed.checkpoint_meta(), next_job=killed.next_job)   # written before its jobs
    out = killed.tick(0.0)
    old = next(j for j, job in killed.jobs.items() if job.kind == "photon")
    ckpt = tmp_path / "ckpt"
    ckpt.mkdir()
    resumed = new_state()
    resumed.resume(doc, first_job=checkpoint.claim_job_ids(str(ckpt), doc))
    _register(resumed, "a")
    resumed.cull_box, resumed.eye_completed = killed.cull_box, 1
    resumed.tick(0.0)
    assert resumed.first_job == checkpoint.ID_BLOCK and old not in resumed.jobs
    resumed.on_message("a", _results([old], [killed.jobs[old].paths], deposits_job=[old] * 3,
                                      credit=_shares(out, old)), 0.1)
    k = resumed.counters
    assert k["deposits_stale"] == 3 and k["deposits_received"] == 0 and k["deposits_late"] == 0
    assert k["photons_completed"] == 0 and k["over_credited_jobs"] == 0


def test_each_resume_from_one_checkpoint_claims_a_block_of_its_own(tmp_path):
    doc = {"first_job": 0, "next_job": 123}
    firsts = [checkpoint.claim_job_ids(str(tmp_path), doc) for _ in range(3)]
    assert firsts == [checkpoint.ID_BLOCK, 2 * checkpoint.ID_BLOCK, 3 * checkpoint.ID_BLOCK]
    # A checkpoint written by the third server: the next block is past it.
    assert checkpoint.claim_job_ids(str(tmp_path), {"first_job": firsts[2], "next_job": firsts[2] + 9}) \
        == 4 * checkpoint.ID_BLOCK
    (tmp_path / checkpoint.IDS_FILE).write_bytes(b"\xc1garbage")
    with pytest.raises(checkpoint.CheckpointError, match="job-ids.msgpack: unreadable"):
        checkpoint.claim_job_ids(str(tmp_path), doc)


def _complete_eye_jobs(state, out, e: int, now: float) -> None:
    """Every eye job of iteration e sent in `out` ends with all its credit."""
    for j in sorted({jj for o in out if o.type == "eye_job" and o.fields["eye_iteration"] == e
                     for jj in o.fields["credit_job"].tolist()}):
        state.on_message("a", _results([j], [state.jobs[j].paths], credit=_shares(out, j)), now)


def test_eye_iterations_in_flight_replace_the_hit_points_in_order():
    """Issue 31: several eye iterations are traced at once, and one whose
    paths all ended before an earlier one's waits for it: every pixel gets
    one eye sample per installed iteration, whatever its paths' speed."""
    state = new_state((1, 1, 1))
    state.eye_in_flight = 2
    _register(state, "a")
    out = state.tick(0.0)
    _complete_eye_jobs(state, out, 0, 0.1)
    assert [u.eye_iteration for u in state.updates if u.kind == "hits"] == [0]
    state.cull_box = np.array([[-1e9] * 3, [1e9] * 3])
    sent, now = [], 0.2
    while len(state.eyes) < 2 and now < 5.0:      # photons emitted start iterations 1 and 2
        sent += state.tick(now)
        now += 0.1
        for t in state.tracers.values():
            t.sent_since_report = 0               # as if the tracer had reported an empty queue
    assert sorted(state.eyes) == [1, 2]
    # As many photons as an iteration emitted since (the jobs in flight
    # are all there may be): still no third while two are in flight.
    state.counters["photons_emitted"] += state.settings.photons_per_iteration
    assert not [o for o in state.tick(now) if o.type == "eye_job"] and state.eye_started == 3
    _complete_eye_jobs(state, sent, 2, now)
    assert sorted(state.eyes) == [1, 2] and [u.eye_iteration for u in state.updates if u.kind == "hits"] == [0]
    _complete_eye_jobs(state, sent, 1, now + 0.1)
    assert not state.eyes and state.eye_completed == 3
    assert [u.eye_iteration for u in state.updates if u.kind == "hits"] == [0, 1, 2]
    assert [o for o in state.tick(now + 0.2) if o.type == "eye_job"] and state.eye_started == 4
