"""What the status page shows beyond one snapshot of `ServerState.status()`:
throughput and the mean pixel radius over the whole render, how far the
render is towards the limit that stops it, per tracer its busy share, rays
traced per second, heartbeat age and state, who holds each chunk, and
recent warnings (evictions, rejoins, refusals, lost or timed-out jobs).

The server's loop thread calls `StatusHistory.update` on every status it
publishes (twice a second). It reads the state and touches no socket and
no lock. Memory stays bounded however long the render runs and however
often tracers come and go:

- `History` holds at most `capacity` samples, one per `interval_s` at
  most. When full it drops every other sample and doubles the interval, so
  the whole render stays covered at a coarser step. Samples are cumulative
  counts, so a rate between any two kept samples is exact, whatever was
  dropped between them.
- Warnings and evictions are rings; rate windows and rejoin times are kept
  only for the tracers registered now (or rejoined in the last
  REJOINED_SHOW_S).

Tracer states, as the page shows them: what took most of a tracer's time
over its last RATE_WINDOW_S of heartbeats, from the time it reports
(`TracerRates.split`), unless one of the last three applies:
    tracing   tracing rays (its steps, less the waits for chunk loads)
    loading   waiting for a chunk to be read and its BVH built
    waiting   neither: reading and sending messages, or a full pipe to a peer
    idle      nothing queued to trace (waiting for work)
    silent    no heartbeat for SILENT_S: it is evicted at --tracer-timeout
    rejoined  registered again (cut off, hung or restarted) in the last
              REJOINED_SHOW_S
    evicted   dropped by the server (listed under `evictions`, not `tracers`)
"""
from __future__ import annotations

import math
from collections import deque

HISTORY_SAMPLES = 600
SAMPLE_INTERVAL_S = 1.0
# Rates on the charts and per tracer are taken over this window: hit points
# arrive one eye iteration at a time, and per-second rates would be spikes.
RATE_WINDOW_S = 5.0
SILENT_S = 3.0               # three heartbeat intervals without one
REJOINED_SHOW_S = 30.0
WARNINGS_KEPT = 50
WARNINGS_SHOWN = 20
EVICTIONS_KEPT = 32
CHUNK_ROWS = 256             # the status of a scene of thousands of chunks stays small

# Counters whose growth is worth a warning: counter -> what it means.
COUNTER_WARNINGS = {
    "refused": "refused {n}: a registration past the tracer limit, or results out of range "
               "(see the server's log)",
    "jobs_timed_out": "jobs in flight re-emitted: a job made no progress for too long",
    "job_messages_lost": "{n} job message(s) lost on the way to a tracer: jobs in flight re-emitted",
    "welcomes_resent": "a tracer missed its welcome: welcomed again, jobs in flight re-emitted",
    "undeliverable": "{n} message(s) to a tracer could not be delivered",
}


class History:
    """Cumulative photons and hit points and the mean pixel radius, sampled
    at most every `interval_s`, in at most `capacity` samples."""

    def __init__(self, capacity: int = HISTORY_SAMPLES, interval_s: float = SAMPLE_INTERVAL_S):
        if capacity < 2 or not interval_s > 0:
            raise ValueError("a history needs room for two samples and a positive interval")
        self.capacity, self.interval_s = int(capacity), float(interval_s)
        self.samples: list[tuple[float, int, int, float | None]] = []   # t, photons, hit points, radius

    def add(self, t: float, photons: int, hit_points: int, mean_radius: float | None = None) -> bool:
        """Record a sample unless the last is less than `interval_s` old;
        True if it was recorded."""
        if self.samples and t - self.samples[-1][0] < self.interval_s:
            return False
        self.samples.append((float(t), int(photons), int(hit_points), mean_radius))
        if len(self.samples) > self.capacity:
            # The newest stays, and every other one back from it.
            self.samples = self.samples[::-2][::-1]
            self.interval_s *= 2
        return True

    def series(self, window_s: float = RATE_WINDOW_S) -> dict:
        """Per sample after the first: its time, photons/s and hit points/s
        since the latest sample at least `window_s` older (or the first),
        and the mean radius then (None before the first radius)."""
        s = self.samples
        out: dict[str, list] = {"t": [], "photons_per_s": [], "hit_points_per_s": [], "mean_radius": []}
        j = 0
        for i in range(1, len(s)):
            while j + 1 < i and s[i][0] - s[j + 1][0] >= window_s:
                j += 1
            dt = s[i][0] - s[j][0]
            out["t"].append(round(s[i][0], 2))
            out["photons_per_s"].append(round((s[i][1] - s[j][1]) / dt, 1))
            out["hit_points_per_s"].append(round((s[i][2] - s[j][2]) / dt, 1))
            r = s[i][3]
            out["mean_radius"].append(None if r is None or not math.isfinite(r) else float(f"{r:.5g}"))
        return out


class TracerRates:
    """Per tracer, its heartbeats of the last `window_s`: the busy share,
    rays and photon rays traced per second over them (heartbeats carry
    running totals)."""

    def __init__(self, window_s: float = RATE_WINDOW_S):
        self.window_s = window_s
        self.beats: dict[str, deque] = {}

    def observe(self, tid: str, at_s: float, status: dict) -> None:
        busy, rays = status.get("busy_s"), status.get("rays_traced")
        photons = int(status.get("photons_traced", 0))
        if busy is None or rays is None:
            return
        beats = self.beats.setdefault(tid, deque())
        if beats and at_s <= beats[-1][0]:
            return                      # the heartbeat seen last time
        if beats and (busy < beats[-1][1] or rays < beats[-1][2] or photons < beats[-1][3]):
            beats.clear()               # a restarted tracer process counts from zero
        beats.append((at_s, float(busy), int(rays), photons, float(status.get("load_wait_s", 0.0)),
                      float(status.get("idle_s", 0.0))))
        while len(beats) > 2 and at_s - beats[1][0] >= self.window_s:
            beats.popleft()

    def rates(self, tid: str) -> tuple[float | None, float | None, float | None]:
        """(busy share 0..1, rays/s, photon rays/s), None until two
        heartbeats came."""
        beats = self.beats.get(tid)
        if not beats or len(beats) < 2:
            return None, None, None
        (t0, b0, r0, p0, *_), (t1, b1, r1, p1, *_) = beats[0], beats[-1]
        dt = t1 - t0
        # Its clock times the busy seconds, ours the heartbeats: clamp the jitter.
        return min(1.0, max(0.0, (b1 - b0) / dt)), (r1 - r0) / dt, (p1 - p0) / dt

    def split(self, tid: str) -> dict | None:
        """Shares of its time over the window: tracing (its steps less the
        waits for chunk loads), loading (those waits), idle (nothing to
        trace) and waiting (the rest: messages, full pipes); None until
        two heartbeats came."""
        beats = self.beats.get(tid)
        if not beats or len(beats) < 2:
            return None
        (t0, b0, _, _, w0, i0), (t1, b1, _, _, w1, i1) = beats[0], beats[-1]
        dt = t1 - t0
        loading = min(1.0, max(0.0, (w1 - w0) / dt))
        tracing = min(1.0 - loading, max(0.0, (b1 - b0 - (w1 - w0)) / dt))
        idle = min(1.0 - loading - tracing, max(0.0, (i1 - i0) / dt))
        return {"tracing": round(tracing, 3), "loading": round(loading, 3), "idle": round(idle, 3),
                "waiting": round(max(0.0, 1.0 - tracing - loading - idle), 3)}

    def keep_only(self, ids) -> None:
        for tid in set(self.beats) - set(ids):
            del self.beats[tid]


def progress(elapsed_s: float, limits: dict, done: dict, rates: dict) -> dict:
    """How far the render is towards the limit that stops it first.
    `limits`: {"time" | "photons" | "iterations": limit or None}; `done`:
    the same keys' values so far (whole render, resumed part included);
    `rates`: their growth per second in this run. The stop is the limit
    with the shortest ETA (the most advanced one while no rate is known)."""
    out = {"elapsed_s": round(elapsed_s, 3), "stop": None, "limit": None, "value": None,
           "fraction": None, "eta_s": None}
    best = None
    for stop, limit in limits.items():
        if limit is None:
            continue
        value = done[stop]
        fraction = min(1.0, value / limit) if limit > 0 else 1.0
        left = max(0.0, limit - value)
        eta = left / rates[stop] if rates[stop] > 0 else (0.0 if left == 0 else None)
        key = (eta is None, eta or 0.0, -fraction)
        if best is None or key < best[0]:
            best = key, dict(stop=stop, limit=limit, value=value, fraction=round(fraction, 4), eta_s=eta)
    if best is not None:
        out.update(best[1])
    return out


def chunk_table(state, most: int = CHUNK_ROWS) -> list[dict]:
    """Per chunk (the first `most`): the tracers serving it, those that hold
    it in memory, and the portal rays into and out of it, summed over the
    tracers' heartbeats (`portal_by_chunk`: [chunk, in, out] rows; a tracer
    counts what it traced, also of chunks it served earlier)."""
    resident = {t.id: set(t.status.get("resident", ())) for t in state.tracers.values()}
    portal: dict[int, list[int]] = {}
    for t in state.tracers.values():
        for k, rays_in, rays_out in t.status.get("portal_by_chunk", ()):
            c = portal.setdefault(int(k), [0, 0])
            c[0], c[1] = c[0] + int(rays_in), c[1] + int(rays_out)
    rows = []
    for k, owners in enumerate(state.owners[:most]):
        serving = [state.tracers[i] for i in owners if i in state.tracers]
        rays_in, rays_out = portal.get(k, (0, 0))
        rows.append({"chunk": k, "tracers": list(owners),
                     "resident": [t.id for t in serving if k in resident[t.id]],
                     "portal_rays_in": rays_in, "portal_rays_out": rays_out})
    return rows


class StatusHistory:
    """What the server adds to each status it publishes (see the module
    docstring). Times `t_s` are seconds on the server's clock since
    `origin_s`, the status's `server_s`; history times are render seconds."""

    def __init__(self, origin_s: float, capacity: int = HISTORY_SAMPLES):
        self.origin_s = origin_s
        self.history = History(capacity)
        self.rates = TracerRates()
        self.warnings: deque = deque(maxlen=WARNINGS_KEPT)
        self.evictions: deque = deque(maxlen=EVICTIONS_KEPT)
        self.rejoined_at: dict[str, float] = {}
        self._counters: dict[str, int] = {}
        self._evicted_seen = 0
        self._rejoins_seen: dict[str, float] = {}
        self._present: dict[str, int] = {}       # tracer id -> its index, as last seen
        self._notes: set[str] = set()
        self._series = self.history.series()

    def warn(self, now: float, kind: str, text: str) -> None:
        self.warnings.append({"t_s": round(now - self.origin_s, 2), "kind": kind, "text": text})

    def update(self, st: dict, now: float, state, render_s: float | None, mean_radius: float | None,
               counters: dict, notes: tuple = ()) -> None:
        """Add to status `st` (its `phase` and `tracers` already there) what
        the page needs at `now`; `render_s`: seconds since the render
        started (None before); `counters`: the state's and the shell's;
        `notes`: lines to warn about once each."""
        self._watch(now, state, counters, notes)
        if render_s is not None and self.history.add(render_s, counters["photons_emitted"],
                                                     counters["hit_points"], mean_radius):
            self._series = self.history.series()
        per_tracer = self._tracer_fields(now, state)
        st["tracers"] = [dict(row, **per_tracer.get(row.get("id"), {})) for row in st.get("tracers", [])]
        st.update(server_s=round(now - self.origin_s, 2), history=self._series,
                  warnings=list(self.warnings)[::-1][:WARNINGS_SHOWN],
                  evictions=list(self.evictions), chunk_table=chunk_table(state))

    def _tracer_fields(self, now: float, state) -> dict[str, dict]:
        """Per registered tracer id: heartbeat_age_s, busy, time (shares), rays_per_s, state."""
        out = {}
        for t in state.tracers.values():
            self.rates.observe(t.id, t.status_s, t.status)
            busy, rays, photons = self.rates.rates(t.id)
            split = self.rates.split(t.id)
            heard = max(t.status_s, t.welcomed_s)
            out[t.id] = {"heartbeat_age_s": round(now - t.status_s, 2) if t.status_s > -1e29 else None,
                         "busy": None if busy is None else round(busy, 3),    # tracing + loading
                         "time": split,
                         "rays_per_s": None if rays is None else round(rays, 1),
                         "photons_per_s": None if photons is None else round(photons, 1),
                         "state": self._tracer_state(now, t, split, heard)}
        self.rates.keep_only(state.tracers)
        return out

    def _tracer_state(self, now: float, t, split: dict | None, heard: float) -> str:
        if now - self.rejoined_at.get(t.id, -math.inf) < REJOINED_SHOW_S:
            return "rejoined"
        if now - heard > SILENT_S:
            return "silent"
        if split is None:
            return "idle"
        return max(("tracing", "loading", "waiting", "idle"), key=lambda k: split[k])

    def _watch(self, now: float, state, counters: dict, notes: tuple) -> None:
        """Warnings for what changed since the last call."""
        for e in state.evicted[self._evicted_seen:]:
            self.evictions.append(dict(e, t_s=round(now - self.origin_s, 2)))
            self.warn(now, "evicted", f"tracer {e['id']} evicted: {e['reason']}")
        self._evicted_seen = len(state.evicted)
        for tid, at in state.rejoined.items():
            if self._rejoins_seen.get(tid) != at:
                self._rejoins_seen[tid], self.rejoined_at[tid] = at, now
                self.warn(now, "rejoined", f"tracer {tid} registered again: jobs in flight re-emitted")
        evicted_ids = {e["id"] for e in self.evictions}
        for tid, t in state.tracers.items():
            if tid in evicted_ids and self._present.get(tid) != t.index:
                self.rejoined_at[tid] = now
                self.warn(now, "rejoined", f"tracer {tid} rejoined after its eviction")
        self._present = {tid: t.index for tid, t in state.tracers.items()}
        self.rejoined_at = {k: v for k, v in self.rejoined_at.items() if now - v < REJOINED_SHOW_S}
        for name, text in COUNTER_WARNINGS.items():
            n = counters.get(name, 0) - self._counters.get(name, 0)
            if n > 0:
                self.warn(now, name, text.format(n=n))
            self._counters[name] = counters.get(name, 0)
        for line in notes:
            if line and line not in self._notes and len(self._notes) < WARNINGS_KEPT:
                self._notes.add(line)
                self.warn(now, "note", line)
