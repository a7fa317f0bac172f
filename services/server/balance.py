"""Which tracer serves each chunk: round robin at the start (Günther &
Grosch §3.1), then by measured work; which chunks the lights lie in
(their tracers emit the photon jobs), and which chunk each eye tile's
rays start in (its tracers make the tile's rays).

Round robin in index order gives each tracer as many chunks, whatever
work the lights and the camera give each. On the 5M-triangle building
(8 and 16 chunks, 2 tracers, every chunk resident) one tracer traced
14-24% more rays than the other, which was busy 76-82% of the render. So
the server re-assigns by the rays the tracers report traced in each chunk:
chunks move (or swap) off the busiest tracer while that lowers its rays
per core, starting from the current table, so that few chunks move. A
chunk's rays are demand: every path must be traced wherever it goes, so
they do not depend on who traces them (the seconds spent do: a tracer
with little work traces smaller, slower batches). Packages queued for a
chunk that moved are handed to its new owner (`TracerState.set_peers`).

Only when every tracer can hold every chunk: out of core a tracer's time
goes to chunk loads as well, a move costs a load and upsets its pacing,
and balanced rays left one tracer busy 69-77% against 92% without
(`dosppm render` of the building at --memory 200MiB, 2 runs each).
"""
from __future__ import annotations

import numpy as np

from dosppm_core.chunks.view import start_chunks
from dosppm_core.scene.model import LIGHT_DIRECTIONAL, LIGHT_ENV, LIGHT_TRIANGLE
from dosppm_core.trace import eye_ray_job

# Re-assign at most this often, and only when the busiest tracer's share
# of the rays would fall by at least MIN_GAIN: every move makes the new
# owner load the chunk, and its queued packages travel once more.
REBALANCE_INTERVAL_S = 10.0
FIRST_REBALANCE_S = 3.0          # after the start: the first table is the most uneven
MIN_GAIN = 0.03
MIN_MEASURED_RAYS = 1_000_000    # summed over tracers, before the counts say anything


def light_chunks(header, tree) -> list[int]:
    """The chunks the lights' centroids lie in (every chunk if none does):
    photon paths start there, so the tracers serving them make the photon
    jobs' photons and keep most of them in their own queues."""
    lights = header.lights
    if np.any((lights.kind == LIGHT_DIRECTIONAL) | (lights.kind == LIGHT_ENV)):
        return list(range(tree.chunk_count))     # their photons enter the scene anywhere
    centre = np.where((lights.kind == LIGHT_TRIANGLE)[:, None],
                      (lights.p0 + lights.p1 + lights.p2) / 3, lights.p0)
    k = tree.locate(centre, np.zeros_like(centre))
    return sorted(set(k[k >= 0].tolist())) or list(range(tree.chunk_count))


def tile_chunks(header, tree, seed: int, tile_pixels: int) -> list[int]:
    """The chunk most of each eye tile's rays start in (-1: all miss the
    scene), from the first iteration's rays: its tracers make the tile's
    rays and keep most in their own queues. Later iterations jitter the
    rays within their pixels, so a few start elsewhere and are passed on.
    Tile by tile (any camera: a perspective one's rays enter the scene's
    box where they may, an orthographic one's start all over)."""
    n = int(header.camera.width) * int(header.camera.height)
    out = []
    for start in range(0, n, tile_pixels):
        routed, _lost = start_chunks(tree, eye_ray_job(header, seed, 0, start, min(tile_pixels, n - start)))
        out.append(max(routed, key=lambda k: (len(routed[k]), -k)) if routed else -1)
    return out


def assign_chunks(chunk_count: int, ids: list[str]) -> list[list[str]]:
    """Who serves each chunk, round robin over the tracers in join order."""
    n = len(ids)
    if n == 0:
        return [[] for _ in range(chunk_count)]
    if chunk_count >= n:
        return [[ids[k % n]] for k in range(chunk_count)]
    return [[ids[i] for i in range(n) if i % chunk_count == k] for k in range(chunk_count)]


def chunk_work(statuses: list[dict], chunk_count: int) -> list[float]:
    """Rays traced in each chunk, summed over the tracers' reports
    ("rays_by_chunk": [[chunk, rays], ...])."""
    work = [0.0] * chunk_count
    for status in statuses:
        for k, rays in status.get("rays_by_chunk", ()):
            if 0 <= int(k) < chunk_count:
                work[int(k)] += float(rays)
    return work


def by_work(work: list[float], cores: dict[str, int], start: list[str] | None = None) -> list[str]:
    """The tracer of each chunk, balancing work per core: from `start` (a
    tracer per chunk) or, without one, longest processing time first
    (heaviest chunk to the least loaded tracer), then chunks moved or
    swapped off the busiest tracer while that lowers its work per core.
    Deterministic: the same work gives the same table."""
    ids = list(cores)
    load = {t: 0.0 for t in ids}
    if start is None:
        owner = [ids[0]] * len(work)
        for k in sorted(range(len(work)), key=lambda k: (-work[k], k)):
            owner[k] = min(ids, key=lambda t: (load[t] + work[k]) / max(1, cores[t]))
            load[owner[k]] += work[k]
    else:
        owner = list(start)
        for k, t in enumerate(owner):
            load[t] += work[k]
    for _ in range(2 * len(work)):
        if not _improve(owner, work, cores, load):
            break
    return owner


def _improve(owner: list[str], work: list[float], cores: dict[str, int], load: dict[str, float]) -> bool:
    """The one move or swap that most lowers the busiest tracer's work
    per core without another tracer taking its place; False if none does."""
    def per(t, extra=0.0):
        return (load[t] + extra) / max(1, cores[t])
    top = max(cores, key=per)
    best, best_max = None, per(top)
    mine = [k for k, t in enumerate(owner) if t == top]
    for other in cores:
        if other == top:
            continue
        theirs = [None] + [k for k, t in enumerate(owner) if t == other]
        for a in mine:
            for b in theirs:
                d = work[a] - (work[b] if b is not None else 0.0)
                worst = max(per(top, -d), per(other, d))
                if d > 0 and worst < best_max - 1e-9 * best_max:
                    best, best_max = (a, b, other, d), worst
    if best is None:
        return False
    a, b, other, d = best
    owner[a] = other
    if b is not None:
        owner[b] = top
    load[top] -= d
    load[other] += d
    return True


def busiest_share(owner: list[str], work: list[float], cores: dict[str, int]) -> float:
    """The largest work per core of any tracer under `owner` (a tracer per
    chunk), over the mean work per core: 1 is a perfect balance."""
    mean = sum(work) / max(1, sum(cores.values()))
    per = {t: 0.0 for t in cores}
    for k, t in enumerate(owner):
        per[t] += work[k]
    return max(per[t] / max(1, cores[t]) for t in cores) / mean if mean > 0 else 0.0


def rebalanced(owners: list[list[str]], statuses: dict[str, dict], cores: dict[str, int]) -> list[list[str]] | None:
    """A better table than `owners` for the rays the tracers (id: last
    status) report, or None: a tracer out of core (or not saying), too
    little measured, fewer chunks than tracers (they share chunks
    already), or a gain below MIN_GAIN."""
    if len(cores) < 2 or len(owners) < len(cores) or any(len(o) != 1 or o[0] not in cores for o in owners):
        return None
    if not all("rays_by_chunk" in statuses.get(t, {}) and statuses[t].get("holds_every_chunk") for t in cores):
        return None
    work = chunk_work(list(statuses.values()), len(owners))
    if sum(work) < MIN_MEASURED_RAYS:
        return None
    now = [o[0] for o in owners]
    new = by_work(work, cores, start=now)
    if busiest_share(new, work, cores) >= busiest_share(now, work, cores) * (1.0 - MIN_GAIN):
        return None
    return [[t] for t in new]
