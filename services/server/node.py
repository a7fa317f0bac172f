"""The server process: `ServerState` behind a ZeroMQ ROUTER (`dosppm server`).

One thread runs the message loop: receive, feed the state, send what it
returns (never blocking on a tracer: each has an outbox), and every so
often report progress, write snapshots and check the stop limits. A second
thread applies the statistics updates the state hands over (server
batching, §4.3); their kernels release the GIL, so heartbeats, status and
deposits keep flowing during an update, and emission pauses while updates
queue up rather than letting deposits pile up in memory. A third serves
the read-only HTTP status page.

The render stops at a time, photon or iteration limit, or on SIGINT /
SIGTERM: emission stops, every job in flight is awaited (up to a drain
timeout), the last partial batch is applied and the image is written. A
second signal skips the wait; the image so far is written in every case.
A time limit is a deadline (dosppm_core/modes/deadline.py): emission stops
when the queued rays would take past it, and whatever is still in flight
when only the time to apply the last batch and write the image is left of
its grace is discarded whole, job by job, and counted (`jobs_abandoned`).
"""
from __future__ import annotations

import logging
import os
import queue
import signal
import threading
import time
from collections import deque

import numpy as np

from dosppm_core.film import encode_png, tonemap_srgb8, write_exr, write_png
from dosppm_core.kernels import run_serially
from dosppm_core.modes.deadline import grace_s
from dosppm_core.settings import Progress, RenderSettings
from services import transport, wire
from services.ledger import Ledger
from services.server import checkpoint, costs
from services.server.history import StatusHistory, progress
from services.server.options import ServerOptions
from services.server.http import StatusServer
from services.server.state import ServerState, Update
from services.server.statistics import ServerStatistics, moves_box

log = logging.getLogger("dosppm.server")
ACCEPT = {"register", "heartbeat", "results", "chunk_request", "error", "epoch_sums", "eye_light"}
STATUS_INTERVAL_S = 0.5
PROGRESS_INTERVAL_S = 1.0
MAX_UPDATES_QUEUED = 2       # statistics updates waiting before emission pauses
# Besides the last updates, to write the image, tell the tracers and see
# them exit (measured 0.5-0.8 s on the 300k building, 96x72, 2 tracers).
FINISH_S = 1.2


class ServerProcess:
    def __init__(self, store, settings: RenderSettings, options: ServerOptions | None = None,
                 resume: dict | None = None, reporter=None, say=None, context: transport.Context | None = None):
        """`options`: services/server/options.py; `resume`: a checkpoint's
        document; `reporter` takes progress lines, `say` lines for the user
        (what the server waits for)."""
        o = self.options = options or ServerOptions()
        self.store, self.settings = store, settings
        self.say = say or (lambda *parts: None)
        self._said_waiting: str | None = None
        self.out, self.exposure, self.reporter = o.out, o.exposure, reporter
        self.limits = o.limits
        self.snapshot_interval_s, self.drain_timeout_s = o.snapshot_interval_s, o.drain_timeout_s
        self.state = ServerState(store.header, store.tree, settings, store.key, store.manifest, o)
        book = None if o.ledger is None else Ledger(
            settings, (store.header.camera.width, store.header.camera.height), o.ledger,
            resume_at=None if resume is None else resume.get("ledger_records"))
        self.statistics = ServerStatistics(store.header, settings, threads=o.threads, ledger=book)
        self.checkpoint_dir, self.checkpoint_interval_s = o.checkpoint_dir, o.checkpoint_interval_s
        if resume is not None:
            checkpoint.restore(self.statistics.stats, resume)
            if "ledger_totals" in resume:
                self.statistics.sppm.restore_totals(resume["ledger_totals"])
            self.state.resume(resume, first_job=resume.get("claimed_first_job"))
        self.router = transport.router(context)
        self.auth = None
        if o.curve_secret:   # CURVE: encrypted, and only listed tracers get in
            if not o.curve_clients:
                raise ValueError("--curve-secret needs --curve-clients (the tracers' public keys)")
            self.auth = transport.start_authenticator(o.curve_clients, context)
            transport.curve_server(self.router, o.curve_secret)
        self.endpoint = self.router.bind(o.bind)
        self.http = StatusServer(self._status_snapshot, self._preview_png, *o.http) if o.http else None
        self._outbox: dict[str, deque] = {}
        self._lost: list[str] = []
        self._updates: queue.Queue = queue.Queue()
        self._boxes, self._applied = queue.Queue(), queue.Queue()   # from the statistics thread (epochs)
        self._status: dict = {}
        self._status_lock = threading.Lock()
        self.history = StatusHistory(origin_s=time.monotonic())
        self._mean_radius: float | None = None     # set on the statistics thread
        self._preview: tuple[float, bytes | None] = (-1e30, None)
        self._signals = 0
        self.watch = None          # () -> error text or None, checked with the status
        self.failure: str | None = None
        self.started_at: float | None = None
        self.finished_at: float | None = None
        self.loop_cpu_s = 0.0            # the message loop thread's CPU, set as it ends
        self.bytes_out = self.undeliverable = 0
        self.bytes_out_by_type: dict[str, int] = {}     # encoded, as queued (chunk files not in it)
        self.job_encoding_cpu_s, self._costs_at = 0.0, {}    # the render's costs (costs.py)

    @property
    def status_url(self) -> str | None:
        return self.http.url if self.http else None

    @property
    def bytes_in(self) -> int:
        return self.router.bytes_in

    # -- the loop ----------------------------------------------------------------------
    def run(self) -> dict:
        """Render until a limit or a signal; write the image; return a summary."""
        worker = threading.Thread(target=self._apply_updates, name="statistics", daemon=True)
        worker.start()
        if self.http:
            self.http.start()
        restore = self._install_signal_handlers()
        try:
            self._serve()
            self.finished_at = time.monotonic()
        finally:
            # The message loop's own CPU (this thread): messages, job making,
            # accounting; the rest of the process's is the statistics'.
            self.loop_cpu_s = time.thread_time()
            self._coalesce_queued_updates()
            if self.checkpoint_dir and self.state.counters["photons_committed"]:
                self._checkpoint()
            self._updates.put(None)
            worker.join()
            # Every photon applied; writing the image and saying goodbye are
            # the end's fixed cost, left out like the start's.
            self._costs_at["end"] = costs.mark(self)
            self.statistics.end_ledger(self.state.counters["deposits_late"])
            self._write_image()
            self._say_goodbye()
            restore()
            if self.http:
                self.http.close()
            self.router.close()
            if self.auth is not None:
                self.auth.stop()
        return self.summary()

    def _serve(self) -> None:
        # This loop's kernels run on small batches beside tracers that
        # hold every core.
        run_serially()
        phase, drain_deadline = "render", None
        last_status = last_progress = last_snapshot = 0.0
        last_checkpoint = time.monotonic()
        while True:
            now = time.monotonic()
            self._receive(now)
            self._send(self.state.tick(now))
            self._pump_updates()
            if self.state.started and self.started_at is None:
                self.started_at = now
                # The render's cost counts from here: the store is loaded, the
                # statistics made and the tracers welcomed; no photon job is
                # made before the first eye iteration's hit points are in.
                self._costs_at["start"] = costs.mark(self)
            if now - last_status >= STATUS_INTERVAL_S:
                last_status = now
                self._publish_status(now, phase if self.state.started else "waiting")
                self._say_waiting()
                self._check_watch()
            if now - last_progress >= PROGRESS_INTERVAL_S and self.reporter and self.started_at:
                last_progress = now
                self.reporter(self.progress())
            if now - last_snapshot >= self.snapshot_interval_s and self.state.eye_completed:
                last_snapshot = now
                self._updates.put(Update("snapshot"))
            if self._checkpoint_due(now - last_checkpoint):
                last_checkpoint = now
                self._checkpoint()
            if phase == "render" and (self._signals or self._limit_reached(now)):
                phase, drain_deadline = "draining", now + self.drain_timeout_s
                self.state.stop_emitting()
            cut = self._past_deadline(now)
            if cut or (phase == "draining" and (self.state.drained or now > drain_deadline
                                                or self._signals > 1)):
                if not self.state.drained:
                    log.warning("stopping with %d jobs in flight%s%s", len(self.state.jobs),
                                ": the time limit's grace is spent" if cut else "", self._none_in_time())
                self.state.stop_emitting()
                self.state.abandon_jobs_in_flight()
                self.state.finish()
                self._pump_updates()
                return

    def _none_in_time(self) -> str:
        c = self.state.counters
        if c["photons_committed"] or not c["photons_emitted"]:
            return ""
        return ("; no photon job completed in time, so the image holds no photons (out of core a job "
                "waits for chunk loads: give --time more)")

    def _say_waiting(self) -> None:
        """A line whenever what the render waits for changes: tracers to
        register, a chunk without a tracer, or the timeout that ended a wait."""
        w = self.state.waiting_for()
        if w is None:       # running: say why a wait ended short, once
            line = self.state.start_note if self._said_waiting else None
        elif "tracers" in w:
            line = f"waiting for tracers: {w['registered']} of {w['min_tracers']} registered"
        else:
            line = f"waiting for a tracer to hold chunk(s) {', '.join(map(str, w['chunk_owners']))}"
        if line is not None and line != self._said_waiting:
            self.say(line)
        self._said_waiting = line

    def _checkpoint_due(self, since_s: float) -> bool:
        return bool(self.checkpoint_dir) and self.checkpoint_interval_s > 0 and \
            since_s >= self.checkpoint_interval_s and self.state.counters["photons_committed"] > 0

    def _checkpoint(self) -> None:
        """Queued behind the updates before it, so it saves exactly the
        photons handed over so far (written on the statistics thread)."""
        self._updates.put(Update("checkpoint", directory=self.checkpoint_dir,
                                 meta=self.state.checkpoint_meta()))

    @property
    def interrupted(self) -> bool:
        return self._signals > 0

    def _check_watch(self) -> None:
        problem = self.watch() if self.watch and not self.failure else None
        if problem:
            log.error("%s: stopping", problem)
            self.failure = problem
            self._signals = 2        # stop now; the image so far is still written

    def _too_late_to_emit(self, now: float) -> bool:
        if self.limits.seconds is None or self.started_at is None or not self.state.eye_completed:
            return False
        return now - self.started_at + self._time_to_drain_s() >= self.limits.seconds

    def _time_to_drain_s(self) -> float:
        """How long the jobs in flight take to complete once emission stops:
        the recent jobs' latency, but no more than twice the slowest
        tracer's queue at its rate and a second for the stragglers, nor
        less than half the latency. While emission goes on a job waits
        behind photons emitted after it at every chunk it reaches; once
        it stops the queues only shrink. Out of core (the 5M building, one
        chunk resident a tracer) jobs took 15.5 s from emission to commit,
        the drain 6 s, and a 60 s render ended at 47.5 s. Gathering at the
        tracers, the epochs still to gather come after (`Epochs.drain_s`)."""
        latency = self.state.latency_estimate_s()
        jobs = min(latency, max(2.0 * self.state.drain_estimate_s() + 1.0, 0.5 * latency))
        return jobs + self.state.epochs_drain_s()     # gathering at the tracers, then their epochs

    def _past_deadline(self, now: float) -> bool:
        """A time limit T is a deadline: the image is written within
        grace_s(T) after it. Past T, what is still in flight is cut once
        only the time to finish is left of the grace: the updates queued
        and the last batch, at the last batch's pace, and FINISH_S. (Not
        before the first hit points: with none there is no image.)"""
        if self.limits.seconds is None or self.started_at is None or not self.state.eye_completed:
            return False
        grace = grace_s(self.limits.seconds)
        finish = FINISH_S + (self._updates.qsize() + 2) * self.statistics.photon_update_s
        return now - self.started_at >= self.limits.seconds + max(0.0, grace - min(finish, grace))

    def _limit_reached(self, now: float) -> bool:
        # A time limit stops emission once a job made now would not complete
        # before it (out of core, jobs wait for chunk loads: made later,
        # they would only be left out at the deadline).
        if self._too_late_to_emit(now):
            return True
        # Never stop before one batch of photons has been applied: a render
        # whose time went to compiling or loading still yields an image.
        if self.started_at is None or not self.state.counters["photons_committed"]:
            return False
        c = self.state.counters
        # Photon and iteration limits count the whole render, resumed part included.
        st = self.state
        # A time limit is met by the time the last job is in, not when
        # emission stops: the rays queued at the tracers (long queues when
        # chunk loads must be hidden) are traced first.
        return self.limits.reached(now - self.started_at + st.drain_estimate_s(),
                                   st.photons_before + c["photons_emitted"],
                                   st.iterations_before + st.eye_completed)

    def _receive(self, now: float) -> None:
        if not self.router.poll(5):
            return
        # Bounded, so ticks and status keep their pace.
        for prefix, msg in self.router.drain(accept=ACCEPT, limit=1000):
            tid = prefix[0].decode("utf-8", "replace")
            if msg.type == "register":
                self._send(self.state.on_register(tid, msg, now))
            elif msg.type == "chunk_request":
                self._send_chunk(tid, msg.chunk)
            elif msg.type == "error":
                log.warning("tracer %s reports: %s", tid, msg.reason)
            else:
                self._send(self.state.on_message(tid, msg, now))

    def _send_chunk(self, tid: str, chunk: int) -> None:
        """A chunk file by index (never by path: no traversal possible)."""
        if not 0 <= chunk < self.store.chunk_count:
            self._queue(tid, wire.encode("error", reason=f"chunk_request: no chunk {chunk} "
                                         f"(store has {self.store.chunk_count})", about="chunk_request"))
            return
        entry = self.store.manifest["chunks"][chunk]
        with open(os.path.join(self.store.path, entry["file"]), "rb") as f:
            data = f.read()
        for frames in wire.chunk_parts(chunk, entry["sha256"], data):
            self._queue(tid, frames)

    def _send(self, outs) -> None:
        last = None      # (type, fields, frames): a broadcast's one message is encoded once
        for o in outs:
            if last is not None and o.fields is last[1] and o.type == last[0]:
                frames = last[2]      # send copies the frames (transport.Socket.send)
            else:
                frames = self._encoded_job(o) if o.type == "photon_job" else wire.encode(o.type, **o.fields)
                last = (o.type, o.fields, frames)
            size = sum(memoryview(f).nbytes for f in frames)
            self.bytes_out_by_type[o.type] = self.bytes_out_by_type.get(o.type, 0) + size
            self._queue(o.dest, frames)
        while self._lost:
            tid = self._lost.pop()
            if tid in self.state.tracers:
                self._send(self.state.evict(tid, "unreachable"))

    @costs.thread_cpu("job_encoding_cpu_s")
    def _encoded_job(self, o) -> list:
        """A photon job message's frames: encoding is part of making photon jobs."""
        return wire.encode(o.type, **o.fields)

    def _queue(self, tid: str, frames) -> None:
        self._outbox.setdefault(tid, deque()).append(frames)
        self._flush(tid)

    def _flush(self, tid: str) -> None:
        """Non-blocking, in order; what the tracer's pipe cannot take yet
        waits in its outbox (bounded by the queue allowance the state gives it)."""
        box = self._outbox[tid]
        while box:
            try:
                self.router.send(box[0], [tid.encode()], block=False)
            except transport.WouldBlock:
                return
            except transport.Unreachable:
                if tid not in self.state.tracers:
                    # A reply to a peer that is gone: an unregistered one, or
                    # the old connection of a tracer that connected again
                    # (libzmq renames it on handover). No job was in it.
                    box.clear()
                    return
                self.undeliverable += len(box)
                log.warning("tracer %s unreachable: %d messages not delivered", tid, len(box))
                box.clear()
                # Jobs may have been in what was lost: drop the tracer (its
                # jobs in flight are re-emitted); it registers again when it
                # hears it is unknown.
                if tid in self.state.tracers:
                    self._lost.append(tid)
                return
            self.bytes_out += sum(memoryview(f).nbytes for f in box.popleft())

    # -- statistics --------------------------------------------------------------------
    def _pump_updates(self) -> None:
        for tid in [t for t, b in self._outbox.items() if b]:
            self._flush(tid)
        while self.state.updates:
            self._updates.put(self.state.updates.popleft())
        while True:
            try:
                box = self._boxes.get_nowait()
            except queue.Empty:
                break
            if box is not None:
                self.state.cull_box = box
        while not self._applied.empty():
            self._send(self.state.on_applied(self._applied.get_nowait()))
        # Server batching's back-pressure (§5.7, the server as bottleneck):
        # stop emitting photons while updates queue, instead of holding ever
        # more deposits.
        self.state.paused = self._updates.qsize() >= MAX_UPDATES_QUEUED

    def _coalesce_queued_updates(self) -> None:
        """At the end, merge runs of queued photon batches into one update
        each: a server that fell behind (tiny --photon-batch) finishes in
        one gather per run instead of one per batch, and the result is the
        same photons applied once."""
        queued = []
        while True:
            try:
                queued.append(self._updates.get_nowait())
                self._updates.task_done()
            except queue.Empty:
                break
        merged: list[Update] = []
        for u in queued:
            if merged and u.kind == "photons" and merged[-1].kind == "photons":
                last = merged[-1]
                merged[-1] = Update("photons", deposits=last.deposits + u.deposits,
                                    photons_emitted=last.photons_emitted + u.photons_emitted,
                                    jobs=_joined_jobs(last.jobs, u.jobs))
            else:
                merged.append(u)
        for u in merged:
            if u.kind != "snapshot":      # the final image is written anyway
                self._updates.put(u)

    def _apply_updates(self) -> None:
        while True:
            u = self._updates.get()
            if u is None:
                return
            if u.kind == "snapshot":
                self._snapshot()
                continue
            try:
                self._boxes.put(self.statistics.apply(u))
                if u.kind in ("hits", "gather", "epoch"):
                    self._applied.put(u)
            except Exception:   # noqa: BLE001 - log and keep the render alive
                log.exception("statistics update failed")
                self._boxes.put(None)
            finally:
                self._updates.task_done()
            if moves_box(u):
                self._measure_radius()

    def _measure_radius(self) -> None:
        """The mean pixel radius for the status page's convergence chart.
        Radii change only here, so one pass after each update (far cheaper
        than the update) keeps it exact without scanning them per request."""
        stats = self.statistics.stats
        with self.statistics.lock:
            mean = float(np.mean(stats.radius)) if stats.has_radius else None
        self._mean_radius = mean

    # -- output ----------------------------------------------------------------------
    def _snapshot(self) -> None:
        """The image so far, written on the statistics thread: it reads the
        statistics under their lock, which an update holds for seconds when
        a flood of deposits is applied (out of core, when the first eye
        iteration completes). Written from the message loop, it waited
        there, without heartbeats; past the tracers' SERVER_SILENT_S they
        register again and every job in flight is re-emitted
        (tests/test_server_protocol.py)."""
        try:
            self._write_image()
        except Exception:   # noqa: BLE001 - a full disk must not end the render, nor this thread
            log.exception("snapshot not written")
        finally:
            self._updates.task_done()

    def _write_image(self) -> None:
        if not self.state.eye_completed or not self.out:
            return
        img = self.statistics.image()
        os.makedirs(os.path.dirname(os.path.abspath(self.out)), exist_ok=True)
        write_exr(self.out, img, self.statistics.layers())
        write_png(os.path.splitext(self.out)[0] + ".png", img, exposure=self.exposure)

    def _say_goodbye(self) -> None:
        reason = "interrupted" if self._signals else "render complete"
        if self.failure:
            reason = f"stopped: {self.failure}"
        # Job messages still waiting for a tracer's pipe carry only jobs
        # that can no longer count: they go no further.
        for box in self._outbox.values():
            box.clear()
        self._send(self.state.shutdown_messages(reason))
        # The goodbyes go out for a moment; with a time limit, the moment
        # is what is left of its grace (0.2 s at least).
        wait = 2.0
        if self.limits.seconds is not None and self.started_at is not None:
            left = self.started_at + self.limits.seconds + grace_s(self.limits.seconds) - time.monotonic()
            wait = min(wait, max(0.2, left))
        deadline = time.monotonic() + wait
        while any(self._outbox.values()) and time.monotonic() < deadline:
            for tid in [t for t, b in self._outbox.items() if b]:
                self._flush(tid)
            time.sleep(0.01)

    # -- status --------------------------------------------------------------------------
    def progress(self) -> Progress:
        s = self.state
        seconds = time.monotonic() - self.started_at if self.started_at else 0.0
        return Progress(s.eye_completed, s.counters["photons_emitted"], s.counters["hit_points"],
                        seconds, {k: v for k, v in s.status()["path_ends"].items()})

    def _publish_status(self, now: float, phase: str) -> None:
        st = self.state.status()
        seconds = now - self.started_at if self.started_at else 0.0
        at = self._progress(seconds, st)
        st.update(phase=phase, seconds=round(seconds, 3), endpoint=self.endpoint,
                  photons_per_s=st["photons_emitted"] / seconds if seconds > 0 else 0.0,
                  hit_points_per_s=st["hit_points"] / seconds if seconds > 0 else 0.0,
                  eta_s=at["eta_s"], progress=at, update_seconds=round(self.statistics.update_seconds, 3),
                  updates_queued=self._updates.qsize(), bytes_in=self.bytes_in, bytes_out=self.bytes_out,
                  cpu_s=round(time.process_time(), 3),
                  undeliverable=self.undeliverable, emission_paused=self.state.paused,
                  failure=self.failure)
        self.history.update(st, now, self.state, seconds if self.started_at else None, self._mean_radius,
                            dict(self.state.counters, undeliverable=self.undeliverable),
                            notes=(self.state.start_note, self.failure))
        with self._status_lock:
            self._status = st

    def _progress(self, seconds: float, st: dict) -> dict:
        """Towards the limit that stops the render first; photons and
        iterations count the whole render, resumed part included, as the
        limits do (`_limit_reached`)."""
        lim, s = self.limits, self.state
        per_s = 1 / seconds if seconds > 0 else 0.0
        return progress(seconds, {"time": lim.seconds, "photons": lim.photons, "iterations": lim.iterations},
                        {"time": seconds, "photons": s.photons_before + st["photons_emitted"],
                         "iterations": s.iterations_before + st["iteration"]},
                        {"time": 1.0, "photons": st["photons_emitted"] * per_s,
                         "iterations": st["iteration"] * per_s})

    def _status_snapshot(self) -> dict:
        with self._status_lock:
            return dict(self._status)

    def _preview_png(self) -> bytes | None:
        """The current image as PNG, made at most every 2 s (HTTP thread)."""
        made, png = self._preview
        if time.monotonic() - made < 2.0:
            return png
        if not self.statistics.stats.has_radius:
            return None
        png = encode_png(tonemap_srgb8(self.statistics.image(), self.exposure))
        self._preview = (time.monotonic(), png)
        return png

    def summary(self) -> dict:
        st = self._status_snapshot() or self.state.status()
        st = dict(st, **self.state.status())
        st["update_seconds"] = self.statistics.update_seconds
        st["photons_applied"] = self.statistics.photons_applied
        st["photons_in_image"] = int(self.statistics.stats.photons_emitted)   # N_e, resumed part included
        st["cpu_s"] = round(time.process_time(), 3)
        st["loop_cpu_s"] = round(self.loop_cpu_s, 3)
        st["bytes_in"], st["bytes_out"] = self.bytes_in, self.bytes_out
        st["bytes_in_by_type"] = dict(self.router.bytes_in_by_type)
        st["bytes_out_by_type"] = dict(self.bytes_out_by_type)
        # Start-up (and the end's image and goodbyes) left out: costs.py.
        end = self._costs_at.get("end") or costs.mark(self)
        st["render_costs"] = costs.since(self._costs_at.get("start"), end)
        if self.started_at is not None:
            # When the render's clock started, as a Unix time: what a time
            # limit counts from (the process's own start-up comes before).
            st["started_unix"] = time.time() - (time.monotonic() - self.started_at)
        if self.started_at is not None and self.finished_at is not None:
            st["seconds"] = self.finished_at - self.started_at   # rendering, drain included
        return st

    # -- signals -------------------------------------------------------------------------
    def _install_signal_handlers(self):
        if threading.current_thread() is not threading.main_thread():
            return lambda: None

        def handler(signum, frame):
            self._signals += 1
            log.warning("signal %d: %s", signum, "stopping" if self._signals == 1 else "stopping now")
        old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
        return lambda: [signal.signal(s, h) for s, h in old.items()]


def _joined_jobs(a: tuple | None, b: tuple | None) -> tuple | None:
    """The committed jobs of two merged photon updates, for the ledger:
    (rng keys, paths, cull boxes), one after the other."""
    if a is None or b is None:
        return a if b is None else b
    return tuple(np.concatenate([x, y]) for x, y in zip(a, b))
