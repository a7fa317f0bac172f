"""The ledger of a render: exactly-once checked from outside the server
(issue 15).

The server's statistics thread records, in the order it applies them,
what each update was made of: the eye iteration whose hit points it
installed, and the photon jobs whose deposits it applied (rng key, paths,
the cull box each was sent with), with the photons emitted for the batch.
At the end it records its totals: deposits applied and their flux, N and
tau summed over the pixels, N_e and hit points.

Photon paths and eye paths are pure functions of (seed, key) and (seed,
iteration, pixel), so `retrace` can redo exactly those steps in one
process, with the library alone and the whole scene in one piece, and
`check` compares its totals with the server's. A job lost, a message
counted twice or deposits dropped on the way change the server's totals
and not the re-trace's.

The file is a stream of msgpack records (arrays as dtype, shape and raw
bytes); never pickle.
"""
from __future__ import annotations

import dataclasses

import msgpack
import numpy as np

from dosppm_core.jobs import PhotonDeposits
from dosppm_core.settings import RenderSettings
from dosppm_core.sppm.iteration import EyePass, SPPMIteration

# Relative tolerance of the float totals: sums in another order, nothing
# more (one job of 1,024 photons in a million is 1e-3).
RTOL = 1e-6


class LedgerError(ValueError):
    """A ledger file that cannot be read; one line naming it."""


def _array(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(a)
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def _from(d: dict) -> np.ndarray:
    return np.frombuffer(d["data"], np.dtype(d["dtype"])).reshape(d["shape"])


class Ledger:
    """Records of a render's updates: to a file at `path` as they happen
    (a killed server leaves every record it applied), else in memory.
    `resume_at`: a resumed render's ledger keeps the first records of the
    file at `path`, those written up to its checkpoint, and goes on."""

    def __init__(self, settings: RenderSettings, path: str | None = None, resume_at: int | None = None):
        self.path, self.records, self.count = path, [], 0
        kept = read(path)[:resume_at] if path and resume_at else []
        self._file = open(path, "wb") if path else None
        for rec in kept or [{"kind": "settings", "settings": dataclasses.asdict(settings)}]:
            self._write(rec)

    def record(self, update) -> None:
        """One applied `state.Update` (checkpoints are not statistics steps)."""
        if update.kind == "hits":
            self._write({"kind": "hits", "eye_iteration": int(update.eye_iteration)})
        elif update.kind == "photons":
            keys, paths, boxes = update.jobs
            self._write({"kind": "photons", "emitted": int(update.photons_emitted), "keys": _array(keys),
                         "paths": _array(paths), "boxes": _array(boxes)})

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


def retrace(scene, records: list[dict]) -> dict:
    """The totals of the ledger's steps redone in this process: every eye
    iteration's tiles traced again, every committed photon job emitted and
    traced again and culled against its own box, and all applied to fresh
    pixel statistics in the ledger's order."""
    from dosppm_core.modes.sppm import Renderer
    settings = RenderSettings(**records[0]["settings"])
    engine = Renderer(scene, dataclasses.replace(settings, threads=2))
    sppm = SPPMIteration(scene, settings, threads=2)
    try:
        for rec in records[1:]:
            if rec["kind"] == "hits":
                sppm.install_eye_pass(_eye_pass(engine, settings, rec["eye_iteration"]))
            elif rec["kind"] == "photons":
                sppm.apply_photon_batch(_photons(engine, settings, rec), rec["emitted"])
    finally:
        engine.close()
    return sppm.totals()


def _eye_pass(engine, settings: RenderSettings, iteration: int) -> EyePass:
    from dosppm_core.trace import eye_ray_job, trace_eye
    cam = engine.scene.camera
    n_pix = int(cam.width) * int(cam.height)
    eye = EyePass(iteration)
    for start in range(0, n_pix, settings.tile_pixels):
        batch = eye_ray_job(engine.scene, settings.seed, iteration, start,
                            min(settings.tile_pixels, n_pix - start))
        hits, (pixels, rgb), _ends = trace_eye(engine.accel, engine.surf, batch, settings.max_depth,
                                               engine.lights)
        eye.add(hits, pixels, rgb)
    return eye


def _photons(engine, settings: RenderSettings, rec: dict) -> PhotonDeposits:
    """The deposits of a batch's jobs, each job traced against its own box
    (jobs sent with the same box are traced together)."""
    from dosppm_core.trace import emit_photon_jobs, trace_photon_jobs
    keys, paths, boxes = _from(rec["keys"]), _from(rec["paths"]), _from(rec["boxes"])
    if len(keys) == 0:             # the last batch of a drained render may commit deposits only
        return PhotonDeposits.empty()
    eps = engine.surf.eps_abs
    out = []
    _, group = np.unique(boxes.reshape(len(boxes), -1), axis=0, return_inverse=True)
    for g in np.unique(group):
        sel = np.flatnonzero(group.ravel() == g)
        batch = emit_photon_jobs(engine.scene, settings.seed, keys[sel], paths[sel], eps)
        deposits, _ends, _culled = trace_photon_jobs(engine.accel, engine.surf, [batch], boxes[sel[0]],
                                                     settings.max_depth,
                                                     deposit_from=settings.deposit_from)
        out.append(deposits)
    return PhotonDeposits.concat(out)


def compare(server: dict, retraced: dict, rtol: float = RTOL) -> list[str]:
    """Where the server's totals and the re-trace's differ; empty if they agree."""
    problems = []
    for k in ("photons_emitted", "hit_points", "deposits"):
        if server[k] != retraced[k]:
            problems.append(f"{k}: server {server[k]:,}, re-traced {retraced[k]:,}")
    for k in ("flux", "N", "tau"):
        a, b = np.atleast_1d(server[k]), np.atleast_1d(retraced[k])
        if not np.allclose(a, b, rtol=rtol, atol=0.0):
            problems.append(f"{k}: server {a.tolist()}, re-traced {b.tolist()}")
    return problems


def check(scene, records: list[dict]) -> list[str]:
    """Problems found re-tracing a finished render's ledger; empty: every
    committed photon counted exactly once, nothing else."""
    end = records[-1]
    if end.get("kind") != "end":
        return ["the ledger has no end record (the server did not finish)"]
    return compare(end["totals"], retrace(scene, records))
