"""The ledger of a render: exactly-once checked from outside the server
(issue 15).

The server's statistics thread records, in the order it applies them,
what each update was made of: the eye iteration whose hit points it
installed, and the photon jobs whose deposits it applied (rng key, paths,
the cull box each was sent with), with the photons emitted for the batch.
At the end it records its totals: deposits applied and their flux, N and
tau summed over the pixels, N_e and hit points.

Photon paths and eye paths are pure functions of (seed, key) and (seed,
iteration, pixel), and of the chunks they cross, so `retrace` can redo
exactly those steps in one process, with one tracer state serving every
chunk and no server, transport or accounting, and `check` compares its
totals with the server's. A job lost, a message
counted twice or deposits dropped on the way change the server's totals
and not the re-trace's.

The file is a stream of msgpack records (arrays as dtype, shape and raw
bytes); never pickle.
"""
from __future__ import annotations

import copy
import dataclasses

import msgpack
import numpy as np

from dosppm_core import arrays
from dosppm_core.jobs import PhotonDeposits
from dosppm_core.settings import RenderSettings
from dosppm_core.sppm.iteration import EyePass

# Relative tolerance of the float totals: sums in another order, nothing
# more (one job of 1,024 photons in a million is 1e-3).
RTOL = 1e-6


class LedgerError(ValueError):
    """A ledger file that cannot be read; one line naming it."""


class Ledger:
    """Records of a render's updates: to a file at `path` as they happen
    (a killed server leaves every record it applied), else in memory.
    `resume_at`: a resumed render's ledger keeps the first records of the
    file at `path`, those written up to its checkpoint, and goes on."""

    def __init__(self, settings: RenderSettings, image: tuple[int, int], path: str | None = None,
                 resume_at: int | None = None):
        """`image`: the render's (width, height), which a chunk store's
        camera need not have (`--width` and `--height` override it)."""
        self.path, self.records, self.count = path, [], 0
        kept = read(path)[:resume_at] if path and resume_at else []
        self._file = open(path, "wb") if path else None
        first = {"kind": "settings", "settings": dataclasses.asdict(settings), "image": list(map(int, image))}
        for rec in kept or [first]:
            self._write(rec)

    def record(self, update) -> None:
        """One applied `state.Update` (checkpoints are not statistics steps)."""
        if update.kind == "hits":
            self._write({"kind": "hits", "eye_iteration": int(update.eye_iteration),
                         "kept": update.hits is not None})
        elif update.kind in ("photons", "epoch"):     # an epoch: its jobs, gathered at the tracers
            keys, paths, boxes = update.jobs
            self._write({"kind": "photons", "emitted": int(update.photons_emitted), "keys": arrays.pack(keys),
                         "paths": arrays.pack(paths), "boxes": arrays.pack(boxes)})

    def end(self, totals: dict) -> None:
        self._write({"kind": "end", "totals": totals})
        if self._file:
            self._file.close()
            self._file = None

    def _write(self, rec: dict) -> None:
        self.count += 1
        if self._file is None:
            self.records.append(rec)
            return
        self._file.write(msgpack.packb(rec, use_bin_type=True))
        self._file.flush()


def read(path: str) -> list[dict]:
    try:
        with open(path, "rb") as f:
            records = list(msgpack.Unpacker(f, raw=False, strict_map_key=False))
    except (OSError, ValueError, msgpack.UnpackException) as e:
        raise LedgerError(f"{path}: not a ledger ({e})") from e
    if not records or not all(isinstance(r, dict) for r in records) or records[0].get("kind") != "settings":
        raise LedgerError(f"{path}: not a ledger (no settings record first)")
    return records


def retrace(provider, records: list[dict], threads: int = 1) -> dict:
    """The totals of the ledger's steps redone in this process: every eye
    iteration's tiles and every committed photon job traced again by one
    tracer state that serves every chunk of `provider` (the render's chunk
    store, or any chunk provider of the same scene: the tracers' own code,
    chunked as theirs was, so each path is bit for bit theirs), deposits
    culled against their own job's box as the server culls them, and all
    applied to fresh pixel statistics in the ledger's order. `threads`:
    the tracers' (Embree's BVH depends on the threads that built it, and a
    tie between two triangles at one distance may then fall otherwise)."""
    from dosppm_core.sppm.iteration import SPPMStatistics
    from services.culling import within_own_boxes
    from services.tracer.state import TracerState
    settings = RenderSettings(**records[0]["settings"])
    header = copy.deepcopy(provider.header)
    header.camera.width, header.camera.height = records[0]["image"]
    tracer = TracerState("ledger", provider, settings.max_depth, threads=threads, direct=settings.direct)
    tracer.set_peers(0, [["ledger"]] * provider.tree.chunk_count)
    sppm = SPPMStatistics(header, settings, threads=2)
    try:
        for rec in records[1:]:
            if rec["kind"] == "hits":
                eye = _eye_pass(tracer, provider.tree, header, settings, rec["eye_iteration"])
                if rec.get("kept", True):
                    sppm.install_eye_pass(eye)
                else:           # an iteration that installs no hit points (`keeps_hit_points`)
                    sppm.add_eye_emission(eye.complete()[1])
            elif rec["kind"] == "photons":
                keys, paths, boxes = (arrays.unpack(rec[k], what=f"ledger record's {k!r}")
                                      for k in ("keys", "paths", "boxes"))
                deposits = _photons(tracer, provider.tree, header, settings, keys, paths, boxes)
                ids = np.arange(len(keys), dtype=np.int64)
                sppm.apply_photon_batch(within_own_boxes(deposits, (ids, keys, paths, boxes)), rec["emitted"])
    finally:
        tracer.close()
    return sppm.totals()


def _run(tracer, field: str) -> list:
    """Step `tracer` until it has no work; the `field` of every results message."""
    out = []
    while tracer.has_work():
        for o in tracer.step():
            if o.type == "results" and o.fields.get(field) is not None:
                out.append(o.fields)
    return out


def _eye_pass(tracer, tree, header, settings: RenderSettings, iteration: int) -> EyePass:
    from dosppm_core.chunks.view import start_chunks
    from dosppm_core.trace import eye_ray_job
    n_pix = int(header.camera.width) * int(header.camera.height)
    for start in range(0, n_pix, settings.tile_pixels):
        batch = eye_ray_job(header, settings.seed, iteration, start, min(settings.tile_pixels, n_pix - start))
        for k, part in start_chunks(tree, batch)[0].items():
            tracer.receive("eye", k, part, eye_iteration=iteration)
    eye = EyePass(iteration)
    for f in _run(tracer, "emitted_pixels"):
        eye.add(f["hits"], f["emitted_pixels"], f["emitted_rgb"])
    return eye


def _photons(tracer, tree, header, settings: RenderSettings, keys, paths, boxes) -> PhotonDeposits:
    """The deposits of a batch's jobs (their `job` column: the job's row in
    the batch), each job fed with its own cull box."""
    from dosppm_core.chunks.view import start_chunks
    from dosppm_core.trace import emit_photon_jobs
    eps = header.spawn_epsilon()
    for m in range(len(keys)):
        batch = emit_photon_jobs(header, settings.seed, keys[m:m + 1], paths[m:m + 1], eps)
        batch.job[:] = m
        for k, part in start_chunks(tree, batch)[0].items():
            tracer.receive("photon", k, part, cull_box=boxes[m])
    return PhotonDeposits.concat([f["deposits"] for f in _run(tracer, "deposits")])


def compare(server: dict, retraced: dict, rtol: float = RTOL) -> list[str]:
    """Where the server's totals and the re-trace's differ; empty if they
    agree. Counts must match exactly; sums of floats (flux, N, tau) within
    `rtol`, as they were added up in another order."""
    problems = []
    for k in ("photons_emitted", "hit_points", "deposits"):
        if server[k] != retraced[k]:
            problems.append(f"{k}: server {server[k]:,}, re-traced {retraced[k]:,}")
    if server.get("deposits_late", 0):
        problems.append(f"deposits_late: the server dropped {server['deposits_late']:,} deposits of jobs "
                        f"already complete")
    if not np.allclose(server["flux"], retraced["flux"], rtol=rtol, atol=0.0):
        problems.append(f"flux: server {server['flux']}, re-traced {retraced['flux']}")
    for k in ("N", "tau"):
        a, b = np.atleast_1d(server[k]), np.atleast_1d(retraced[k])
        if not np.allclose(a, b, rtol=rtol, atol=0.0):
            problems.append(f"{k}: server {a.tolist()}, re-traced {b.tolist()}")
    return problems


def check(provider, records: list[dict]) -> list[str]:
    """Problems found re-tracing a finished render's ledger with the chunks
    of `provider`; empty: every committed photon counted exactly once,
    nothing else."""
    end = records[-1]
    if end.get("kind") != "end":
        return ["the ledger has no end record (the server did not finish)"]
    return compare(end["totals"], retrace(provider, records))
