"""The server's state (Günther & Grosch §3.1 "Network", §3.3, §4.3), apart
from its sockets.

`ServerState` is fed decoded messages and clock ticks and returns `Out`
records to send; the I/O shell (`node.py`) moves frames and runs the
statistics updates it hands over. Its parts, one module each: membership
(membership.py), emission (emission.py), eye scheduling (eye_schedule.py),
the gather at the tracers (epoch_state.py), and here the job records,
exact accounting, batching, the clock and the status. What it does:

- Registration: tracers join at any time; chunks are assigned round robin
  (c >= n: tracer i serves chunks i, i + n, ...; c < n: chunk k is shared
  by tracers k, k + c, ...), and every tracer gets the table of who serves
  which chunk whenever it changes.
- Emission: photon jobs are created while fewer than `min_photon_jobs`
  (§3.3), or than the tracers' queue allowances hold, are in flight, and
  sent as (id, rng key, count) to the tracers of the lights' chunks,
  which make the photons; a tracer whose reported queue plus what was
  sent since passes its queue allowance (the server's, or the longer
  queue it asks for to hide chunk loads) gets nothing more until it
  reports again (back-pressure).
  Eye iterations are split into tiles (§5.6), sent as (id, pixel start,
  count) to the tracers of the chunks their rays start in, which make the
  rays; they run at the same time as photons: the next starts once
  `photons_per_iteration` photons have been emitted since the last one
  started, with up to `eye_in_flight` of them traced at once (the
  paper's §6 future work; out of core, one chunk load then serves
  several). They replace the hit points in order, each once
  all its paths have ended, so every pixel gets one eye sample per
  iteration whatever its paths' speed.
- Exact accounting: the server made every job, so it knows each job's
  path count; tracers report ended paths per job and return the job's
  credit with the messages that carry its deposits; a job is complete when
  all its credit is back (services/credit.py; no timeout). Only then do its photons count as
  emitted (N_e), exactly once, and only complete eye iterations replace
  the hit points.
- Server batching: deposits are held until their job is complete and
  handed over for one statistics update per `photon_batch` deposits (§4.3);
  `finish` hands over the last partial batch.
- Culling: emission jobs carry the hit-point box grown by the largest
  radius (the shell sets it after each update), so tracers cull deposits
  before sending them (§4.3).
"""
from __future__ import annotations

import itertools
from collections import deque

import numpy as np

from dosppm_core.chunks.pacing import default_queue_memory, eye_iterations_in_flight
from dosppm_core.jobs import END_NAMES
from dosppm_core.settings import RenderSettings
from dosppm_core.sppm.iteration import hit_point_stride
from dosppm_core.trace import NO_CULL
from services.credit import by_job
from services.server.balance import light_chunks, tile_chunks
from services.server.emission import EmissionMixin
from services.server.epoch_state import EpochStateMixin
from services.server.eye_light import EyeLightMixin
from services.server.eye_schedule import EyeScheduleMixin
from services.server.held import COMPLETE, DEPOSIT_BYTES, DISCARDED, IN_FLIGHT, HeldDeposits, JobStatus
from services.server.membership import HEARTBEAT_INTERVAL_S, MembershipMixin
from services.server.options import ServerOptions
from services.server.records import EyeIteration, Job, TracerInfo, Update  # noqa: F401 (Update: the shell's)
from services.wire import JOB_MESSAGES, MAX_EMITTED, PROTOCOL_VERSION, Out

# A job untouched this long while every tracer is idle is lost (`_watchdog`).
STALL_S = 4.0
# What the state counts (status "counters", OUT.json).
COUNTERS = ("photons_emitted", "photons_completed", "photons_committed", "photon_jobs_completed",
            "eye_jobs_completed", "hit_points", "deposits_received", "photon_paths_ended", "culled",
            "stale_paths", "over_credited_jobs", "results", "updates", "rebalanced", "photons_discarded",
            "jobs_discarded", "tracers_evicted", "eye_iterations_restarted", "deposits_discarded",
            "deposits_stale", "deposits_late", "refused", "tracers_rejoined", "jobs_timed_out",
            "welcomes_resent", "job_messages_lost", "jobs_abandoned", "photons_abandoned",
            "epoch_rounds_timed_out", "light_rounds_timed_out")
LATENCIES_KEPT = 64           # photon jobs' latencies the deadline's estimate takes the median of
EVICTIONS_SHOWN = 20    # the last evictions in the status, with their reasons

# Tracer heartbeat fields the server passes on in its status.
STATUS_KEYS = ("load", "resident", "busy_s", "steps", "rays_traced", "photons_traced", "portal_by_chunk",
               "portal_rays_out", "portal_rays_in", "chunk_loads", "load_s", "load_wait_s", "wasted_prefetches",
               "queue_target", "idle_s", "receive_s", "step_send_s", "forwarded_rays", "cpu_s", "bytes_to_server",
               "bytes_to_peers", "outbox", "outbox_rays", "rays_by_chunk", "waiting")


class ServerState(MembershipMixin, EmissionMixin, EyeScheduleMixin, EpochStateMixin, EyeLightMixin):
    def __init__(self, header, tree, settings: RenderSettings, store_key: str,
                 manifest: dict | None = None, options: ServerOptions | None = None):
        """`options`: the scheduling ones are read here (services/server/options.py)."""
        o = options or ServerOptions()
        settings = settings.for_image(int(header.camera.width) * int(header.camera.height))
        settings.validate()
        for name in ("photons_per_job", "tile_pixels"):      # a job message's paths (wire.MAX_EMITTED)
            if getattr(settings, name) > MAX_EMITTED:
                raise ValueError(f"{name} must be at most {MAX_EMITTED:,} in the service")
        self.header, self.tree, self.settings = header, tree, settings
        self.store_key, self.manifest = store_key, manifest
        self.min_photon_jobs, self.queue_target = int(o.min_photon_jobs), int(o.queue_target_rays)
        self.min_tracers, self.min_tracers_timeout_s = int(o.min_tracers), o.min_tracers_timeout_s
        self._waiting_since: float | None = None
        self.start_note: str | None = None    # why the render started short of min_tracers
        self.concurrent, self.client_batching = bool(o.concurrent), bool(o.client_batching)
        self.tracer_timeout_s = float(o.tracer_timeout_s)
        self.job_timeout_s = max(30.0, 3 * self.tracer_timeout_s)
        self._now = 0.0
        self.evicted: list[dict] = []
        self.rejoined: dict[str, float] = {}      # tracer id -> when it last registered again (status page)
        self.light_chunks = light_chunks(header, tree)     # their tracers emit the photon jobs
        # Each eye tile's rays start in one chunk, mostly: its tracers make them.
        self.tile_chunks = tile_chunks(header, tree, settings.seed, settings.tile_pixels)
        self.camera_chunks = sorted(set(self.tile_chunks) - {-1}) or list(range(tree.chunk_count))
        self.n_pixels = int(header.camera.width) * int(header.camera.height)
        self.tracers: dict[str, TracerInfo] = {}
        self._indices = itertools.count()
        self.owners: list[list[str]] = [[] for _ in range(tree.chunk_count)]   # tracer ids
        self.table_version = 0
        self.emitting = True
        self.paused = False              # set by the shell while statistics updates queue up
        self.started = False
        self.cull_box: np.ndarray | None = None
        self.jobs: dict[int, Job] = {}
        self.next_job = self.first_job = 0         # job ids are never reused (checkpoint.claim_job_ids)
        self._job_status = JobStatus(0)            # per photon job id: UNKNOWN, IN_FLIGHT, ...
        self._photon_pending: deque = deque()         # job ids created, not yet sent
        self.photon_jobs_in_flight = 0
        self.eyes: dict[int, EyeIteration] = {}          # in flight, by index (oldest first)
        self.eye_in_flight = eye_iterations_in_flight(self.n_pixels, o.held_bytes or default_queue_memory())
        self.photons_before = self.iterations_before = 0    # from a resumed checkpoint
        self._eye_restart = False
        self.eye_started = 0
        self.eye_completed = 0
        self._photons_at_eye_start = 0
        self.held = HeldDeposits(settings.photon_batch, o.held_bytes or default_queue_memory())
        self._ready_emitted, self._ready_jobs = 0, []    # photon paths and jobs complete since the last batch
        self.updates: deque[Update] = deque()
        self._last_heartbeat, self._balanced_at = -1e30, None     # _balanced_at: see _rebalance
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.path_ends = np.zeros(len(END_NAMES), np.int64)
        self._latencies: deque = deque(maxlen=LATENCIES_KEPT)     # of the last photon jobs complete
        self._latency_median: float | None = None
        self.job_making_cpu_s = 0.0     # a part of the server's cost per photon (costs.py)
        self._init_epochs(o.gather_at, o.min_tracers, o.batch_growth, o.held_bytes or default_queue_memory())
        self.hit_point_stride = self._hit_point_stride(o.hit_point_stride)
        self._init_light()

    def _hit_point_stride(self, given: int | None) -> int:
        """One eye iteration in how many installs its hit points
        (`hit_point_stride`). By default: gathering at the tracers, one set
        per epoch (what the wire carries is the point of that mode); the
        paper's gather at the server, every iteration, as the paper (fewer
        sets over a short render sample each pixel's footprint fewer times
        for the photons: tests/test_faults' short renders saw it)."""
        if given is not None:
            if given < 1:
                raise ValueError(f"hit_point_stride must be >= 1, got {given}")
            return int(given)
        if self.epochs is None:
            return 1
        s = self.settings
        return hit_point_stride(self.epochs.jobs_per_epoch * s.photons_per_job,
                                s.for_image(self.n_pixels).photons_per_iteration)

    # -- messages ------------------------------------------------------------------
    def on_message(self, tid: str, msg, now: float) -> list[Out]:
        """A message of a registered tracer, by its handler in `HANDLERS`
        (registration is `on_register`: it is the one an unknown id may send)."""
        t = self.tracers.get(tid)
        if t is None:
            return [Out(tid, "error", dict(reason=f"{msg.type}: tracer {tid!r} is not registered",
                                           about=msg.type))]
        t.last_seen_s = now
        handler = self.HANDLERS.get(msg.type)
        return [] if handler is None else handler(self, t, msg, now)

    def _on_heartbeat(self, t: TracerInfo, msg, now: float) -> list[Out]:
        t.status, t.status_s = dict(msg.status), now
        return self._check_welcomed(t, now) or self._check_delivery(t, now)

    def _on_results_message(self, t: TracerInfo, msg, now: float) -> list[Out]:
        return self._counted(self._on_results(t, msg), now)

    def _on_epoch_sums_message(self, t: TracerInfo, msg, now: float) -> list[Out]:
        return self._on_epoch_sums(t.id, msg)

    HANDLERS = {"heartbeat": _on_heartbeat, "results": _on_results_message,
                "epoch_sums": _on_epoch_sums_message, "eye_light": EyeLightMixin._on_eye_light_message}

    # -- results and exact accounting ----------------------------------------------------
    def _check_results(self, msg) -> str | None:
        """What the wire cannot know: ranges of chunks, pixels, materials."""
        if msg.chunk is not None and msg.chunk >= self.tree.chunk_count:      # None: an emission
            return f"field 'chunk' {msg.chunk} out of range (scene has {self.tree.chunk_count})"
        if msg.hits is not None and len(msg.hits):
            h = msg.hits
            if h.pixel.min() < 0 or h.pixel.max() >= self.n_pixels:
                return "field 'hits.pixel' out of range"
            if h.material.min() < 0 or h.material.max() >= len(self.header.materials.kind):
                return "field 'hits.material' out of range"
        p = msg.emitted_pixels
        if p is not None and len(p) and (p.min() < 0 or p.max() >= self.n_pixels):
            return "field 'emitted_pixels' out of range"
        return None

    def _on_results(self, t: TracerInfo, msg) -> list[Out]:
        problem = self._check_results(msg)
        if problem:
            self.counters["refused"] += 1
            return [Out(t.id, "error", dict(reason=f"results: {problem}", about="results"))]
        t.queued, t.sent_since_report, t.queue_target = msg.queued, 0, msg.queue_target
        t.results += 1
        c = self.counters
        c["results"] += 1
        c["culled"] += msg.culled
        self.path_ends += msg.ends
        if msg.deposits is not None and len(msg.deposits):
            # Only deposits of photon jobs in flight are held: a finished,
            # discarded or never-made job's deposits can never count.
            status = self._job_status(msg.deposits.job)
            live = status == IN_FLIGHT
            deposits = msg.deposits if live.all() else msg.deposits.take(live)
            c["deposits_stale"] += len(msg.deposits) - len(deposits)
            # Of a job already complete: impossible by credit (a duplicated
            # message would do it); counted, and the ledger's check fails.
            c["deposits_late"] += int(np.sum(status == COMPLETE))
            if len(deposits):
                self.held.add(deposits)
                c["deposits_received"] += len(deposits)
        e = self.eyes.get(msg.eye_iteration) if msg.hits is not None else None
        if e is not None:
            e.results.add(msg.hits, msg.emitted_pixels, msg.emitted_rgb)
            c["hit_points"] += max(msg.hit_points_made, len(msg.hits))
        for j, fed, left in zip(msg.job_ids.tolist(), msg.job_fed.tolist(), msg.job_left.tolist()):
            job = self.jobs.get(j)
            if job is None:
                c["stale_paths"] += fed - left      # a finished or unknown job: never counted twice
            elif job.kind == "photon":
                c["photon_paths_ended"] += fed - left
        for j, exps in by_job(msg.credit_job, msg.credit_exp).items():
            self._credit(j, exps)
        self._maybe_batch()
        return []

    def _credit(self, j: int, exps: list[int]) -> None:
        """Credit returned for job j (services/credit.py); once it sums to 1
        and all its paths were sent, the job is complete, with everything it
        produced in hand."""
        job = self.jobs.get(j)
        if job is None:
            return                  # a finished, discarded or unknown job
        job.credit.add(exps)
        job.progress_s = self._now
        if job.credit.over:
            self.counters["over_credited_jobs"] += 1
        if job.credit.complete and job.sent:
            self._complete(j, job)

    def _complete(self, j: int, job: Job) -> None:
        del self.jobs[j]
        if job.kind == "photon":
            self.photon_jobs_in_flight -= 1
            self._job_status.set(j, COMPLETE)
            self.counters["photons_completed"] += job.paths
            self.counters["photon_jobs_completed"] += 1
            self._latencies.append(self._now - job.sent_s)
            self._latency_median = None
            if self.epochs is not None:      # its deposits stay at the tracers, by epoch
                self.epochs.complete(j, job.rng_key, job.paths, job.cull_box)
                return
            self._ready_emitted += job.paths
            self._ready_jobs.append((j, job))
            return
        self.counters["eye_jobs_completed"] += 1
        self.eyes[job.eye_iteration].open_jobs -= 1
        # In order: a later iteration whose paths all ended waits for the
        # earlier ones, so the hit points are replaced one iteration at a time.
        while self.eyes and self.eyes[min(self.eyes)].open_jobs == 0:
            self._finish_eye_iteration(self.eyes.pop(min(self.eyes)))

    def _maybe_batch(self, final: bool = False) -> None:
        """Hand over the deposits of complete jobs once `photon_batch` are
        held (server batching), or their photons number `photon_batch` (those
        depositing nothing, direct light only, must commit too); deposits of
        jobs still in flight wait. Gathering at the tracers: the next epoch's."""
        if self.epochs is not None:
            return self._maybe_gather()
        due = self.held.due(self._now, bool(self._ready_jobs)) or self._ready_emitted >= self.held.photon_batch
        if self.eye_completed == 0 or not (final or due):
            return
        jobs = self._ready_job_columns()
        commit, discarded = self.held.split(self._job_status, jobs, self._now)
        self.counters["deposits_discarded"] += discarded      # lost with a tracer
        self.updates.append(Update("photons", deposits=commit, photons_emitted=self._ready_emitted,
                                   jobs=jobs[1:]))
        self.counters["photons_committed"] += self._ready_emitted
        self._ready_emitted, self._ready_jobs = 0, []

    def _ready_job_columns(self) -> tuple:
        """(ids, rng keys, paths, cull boxes (n, 2, 3)) of the photon jobs
        complete since the last batch, by id."""
        ready = sorted(self._ready_jobs, key=lambda jj: jj[0])
        ids = np.array([j for j, _ in ready], np.int64)
        keys = np.array([job.rng_key for _, job in ready], np.int64)
        paths = np.array([job.paths for _, job in ready], np.int64)
        boxes = np.array([NO_CULL if job.cull_box is None else job.cull_box for _, job in ready],
                         np.float64).reshape(-1, 2, 3)
        return ids, keys, paths, boxes

    # -- the clock ---------------------------------------------------------------------
    def tick(self, now: float) -> list[Out]:
        """Start eye iterations, top up and send photon jobs, heartbeats."""
        return self._counted(self._tick(now), now)

    def _counted(self, out: list[Out], now: float) -> list[Out]:
        """Note every job message on its way to a tracer (see `_check_delivery`)."""
        for o in out:
            if o.type in JOB_MESSAGES and o.dest in self.tracers:
                t = self.tracers[o.dest]
                t.jobs_sent += 1
                t.unacked.append(now)
        return out

    def _tick(self, now: float) -> list[Out]:
        out = []
        self._now = now
        if now - self._last_heartbeat >= HEARTBEAT_INTERVAL_S:
            self._last_heartbeat = now
            out += [Out(tid, "heartbeat", dict(status={})) for tid in self.tracers]
            out += self._evict_silent(now)
            self._watchdog(now)
            out += self._rebalance(now) + self._drop_messages()   # epochs the watchdog discarded
        if not self.started:
            if not self._ready_to_start(now):
                return out
            self.started = True
        if not all(self.owners):
            return out
        out += self._ask_light()
        if not self.emitting:
            # Draining: only jobs re-emitted for a lost tracer still go out.
            # Their photons were emitted once and count towards N_e: left
            # unsent, they would hold the drain until its timeout.
            self._maybe_batch()     # gathering at the tracers: the last epochs close now
            return out + (self._send_photon_jobs() if self._photon_pending else [])
        if not self.concurrent:
            return out + self._alternate()
        out += self._maybe_start_eye_iteration()
        self._maybe_batch()     # held full: jobs may have completed since the last batch
        if self.cull_box is not None and not self.paused:
            self._make_photon_jobs()
            out += self._send_photon_jobs()
        return out

    def _watchdog(self, now: float) -> None:
        """Messages can vanish without any error (queued in a TCP connection
        that libzmq replaces after a cut, between the server and a tracer or
        between two tracers): a job no result has touched for
        `job_timeout_s` is presumed lost with them, or for only STALL_S when
        every tracer reports, in a fresh heartbeat, nothing queued and
        nothing waiting to go to a peer (no one is working on it), and all
        jobs in flight are discarded and re-emitted. Correctness never
        depends on it: a job presumed lost that was only slow has its late
        results ignored. So can a gather's request or a tracer's answer: an
        epoch round unanswered as long is discarded with the jobs in flight
        (its jobs made again: a round cannot be asked twice, as a tracer
        drops an epoch's deposits once it has answered its sums)."""
        limit = STALL_S if self._all_idle(now) else self.job_timeout_s
        if any(job.sent and now - job.progress_s > limit for job in self.jobs.values()):
            self.counters["jobs_timed_out"] += 1
            self._discard_jobs_in_flight()
        elif self.epochs is not None and self.epochs.round_waiting_since(now) > limit:
            self.counters["epoch_rounds_timed_out"] += 1
            self._discard_jobs_in_flight()
        elif self.light.waiting_since(now) > limit:
            self.counters["light_rounds_timed_out"] += 1
            self._discard_jobs_in_flight()

    def _discard_jobs_in_flight(self) -> None:
        if self.epochs is not None:     # the lost tracer's held deposits go with their epochs
            self._discard_epochs()
        self.light.discard()            # and its part of the light of every iteration not applied
        again = []
        for j, job in list(self.jobs.items()):
            if not job.sent:
                continue                      # still at the server: nothing lost
            del self.jobs[j]
            self._job_status.set(j, DISCARDED)
            self.counters["jobs_discarded"] += 1
            if job.kind == "photon":
                self.photon_jobs_in_flight -= 1
                self.counters["photons_discarded"] += job.paths
                again.append(self._new_job("photon", job.paths, rng_key=job.rng_key))
        self._photon_pending.extendleft(reversed(again))
        if self.eyes:
            for j in [j for j, job in self.jobs.items() if job.kind == "eye"]:
                del self.jobs[j]
            self.counters["eye_iterations_restarted"] += len(self.eyes)
            self.eyes.clear()                 # the next tick starts a fresh iteration
            self._eye_restart = True

    def _new_job(self, kind: str, paths: int, eye_iteration: int | None = None,
                 rng_key: int | None = None) -> int:
        j = self.next_job
        self.next_job += 1
        if kind == "photon":
            self._job_status.set(j, IN_FLIGHT)
        self.jobs[j] = Job(kind, paths, eye_iteration=eye_iteration, rng_key=j if rng_key is None else rng_key)
        if kind == "photon":
            self.photon_jobs_in_flight += 1
            if self.epochs is not None:
                self.epochs.made(j)
        return j

    # -- checkpoints ---------------------------------------------------------------------
    def checkpoint_meta(self) -> dict:
        """What a checkpoint needs besides the statistics: ids go on past
        every one used, so a resumed render never traces a photon twice."""
        return {"store_key": self.store_key, "settings": self.settings_dict(),
                "next_job": self.next_job, "first_job": self.first_job,
                "next_eye_iteration": self.eye_started,
                "counters": {"photons": self.photons_before + self.counters["photons_committed"],
                             "eye_iterations": self.iterations_before + self.eye_completed}}

    def settings_dict(self) -> dict:
        s = self.settings
        return {k: getattr(s, k) for k in ("seed", "alpha", "radius", "max_depth", "gather",
                                           "photons_per_iteration", "photons_per_job", "photon_batch",
                                           "tile_pixels", "reorder", "cull")}

    def resume(self, doc: dict, first_job: int | None = None) -> None:
        """Continue after a checkpoint: new job ids start at `first_job`,
        past every id the servers before may have used (the checkpoint's
        next_job is only past those it had used when it was written: the
        tracers may still hold jobs made after it, and their messages must
        not be taken for this server's; checkpoint.claim_job_ids)."""
        self.next_job = self.first_job = int(doc["next_job"] if first_job is None else first_job)
        self._job_status = JobStatus(self.first_job)
        self.eye_started = int(doc["next_eye_iteration"])
        self.photons_before = int(doc["counters"]["photons"])
        self.iterations_before = int(doc["counters"]["eye_iterations"])
        self._eye_restart = True      # hit points first: photons wait for their box

    # -- the end ---------------------------------------------------------------------------
    def latency_estimate_s(self) -> float:
        """Seconds from sending a photon job to its completion: the median
        of the last ones complete, or, before any, the age of the oldest in
        flight (it is at least that). A job sent later than this before a
        deadline is unlikely to count. (Jobs made but not sent wait at the
        server, and are dropped when emission stops.)"""
        if self._latencies:
            if self._latency_median is None:      # asked every pass of the loop: made once per change
                self._latency_median = float(np.median(self._latencies))
            return self._latency_median
        made = [job.sent_s for job in self.jobs.values() if job.kind == "photon" and job.sent]
        return self._now - min(made) if made else 0.0

    def drain_estimate_s(self) -> float:
        """Seconds the slowest tracer needs to trace what waits for it, at
        its rate so far (chunk loads included)."""
        worst = 0.0
        for t in self.tracers.values():
            busy, rays = t.status.get("busy_s", 0), t.status.get("rays_traced", 0)
            if busy > 0 and rays > 0:
                worst = max(worst, t.load_estimate * busy / rays)
        return worst

    @property
    def drained(self) -> bool:
        return not self.jobs and self.epochs_drained and self.light.drained

    def abandon_jobs_in_flight(self) -> None:
        """At the deadline: every job still in flight is discarded whole,
        never re-emitted; its deposits held stay out of every batch, its
        photons out of N_e, and a photon job's late results are stale."""
        for j, job in list(self.jobs.items()):
            del self.jobs[j]
            if job.kind == "photon":
                self._job_status.set(j, DISCARDED)
                self.photon_jobs_in_flight -= 1
                if self.epochs is not None:
                    self.epochs.dropped(j)
                self.counters["photons_abandoned"] += job.paths
                self.counters["jobs_abandoned"] += 1
        self.eyes.clear()
        self.light.discard()

    def finish(self) -> None:
        """Hand over the last, partial batch (call once drained)."""
        if self.held.rows or self._ready_emitted:
            self._maybe_batch(final=True)

    def status(self) -> dict:
        c = self.counters
        return {"protocol": PROTOCOL_VERSION, "iteration": self.eye_completed,
                "eye_iterations_in_flight": len(self.eyes),
                "photon_job_latency_s": _quantiles(self._latencies),
                "waiting_for": self.waiting_for(),
                "photons_emitted": c["photons_emitted"], "photons_committed": c["photons_committed"],
                "jobs_in_flight": len(self.jobs), "photon_jobs_in_flight": self.photon_jobs_in_flight,
                "held_bytes": self.held.rows * DEPOSIT_BYTES, "held_full": self.held.full,
                "hit_points": c["hit_points"], "chunks": self.tree.chunk_count,
                "path_ends": {n: int(v) for n, v in zip(END_NAMES, self.path_ends) if n != "continues"},
                "counters": dict(c, **self.light.counters, **(self.epochs.counters if self.epochs else {})),
                "evicted": list(self.evicted[-EVICTIONS_SHOWN:]),
                "tracers": [{"id": t.id, "index": t.index, "endpoint": t.endpoint,
                             "chunks": [k for k, o in enumerate(self.owners) if t.id in o],
                             "queue": t.load_estimate, "rays_sent": t.rays_sent, "results": t.results,
                             **{k: v for k, v in t.status.items() if k in STATUS_KEYS}}
                            for t in sorted(self.tracers.values(), key=lambda t: t.index)]}


def _quantiles(seconds) -> dict | None:
    """Median and 90th percentile of the last photon jobs' latencies (sent
    to complete), for the status page."""
    if not seconds:
        return None
    q = np.quantile(np.asarray(seconds, np.float64), [0.5, 0.9])
    return {"median": round(float(q[0]), 2), "p90": round(float(q[1]), 2)}
