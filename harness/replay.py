"""How many tracers one server core feeds (issue 13): a real server, fed at
full speed by synthetic tracers that replay recorded results.

A synthetic tracer is the real tracer process (`TracerProcess`: the same
registration, heartbeats, wire messages and sockets) whose state traces
its first RECORDED_STEPS photon steps for real and then answers every
photon package at once with one of those results, relabelled to the
package's jobs: its deposits are cycled to the package's size (the
recorded deposits per path), and every path is reported ended, so the
server's exactly-once accounting holds. Eye and shadow rays are traced
for real: they are a small share of a render's rays and their hit points
must be right for the statistics.

Gathering at the tracers, a synthetic tracer gathers its first
RECORDED_EPOCHS epochs for real; with `replay_epochs` it then answers
each epoch's sums with a recorded answer (`ReplayedEpochs`) and keeps no
deposits, so the server meets epochs at the rate the photon accounting
alone allows (benchmarks/slow_link.py: a real tracer's gather would cap
two tracers on this machine far below what the server or the link take).

The server's own counters then give what one server core does at most:
photons applied per second of server CPU, CPU per photon and per results
message, where that CPU goes (the message loop's thread: making photon
jobs, held deposits and the rest; statistics updates; other threads), and
the bytes per photon each way on the wire, all counted from the render's
start (services/server/costs.py: the server's start-up is left out). The
tracer side's rate is the library's photon pass on the same scene with
one thread, measured alone in the same run.

    python -m harness.replay --tracers 2 --seconds 20
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import socket
import subprocess
import sys
import tempfile
import time

import numpy as np

from services.tracer.epochs import EpochDeposits, dense_sums, sparse_sums
from services.tracer.node import TracerError, TracerOptions, TracerProcess
from services.credit import split as split_credit
from services.tracer.state import SERVER, TracerState, concat_credit
from services.wire import Out

RECORDED_STEPS = 16
# Replaying emission too, fewer: a step traced for real on a loaded
# machine takes a second or more, and 16 of them took most of a 15 s run.
RECORDED_STEPS_EMISSION = 2
RECORDED_EPOCHS = 2
REPLAY_RETRY_S = 10.0
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class ReplayState(TracerState):
    """TracerState whose photon steps replay recorded results once
    RECORDED_STEPS of them were traced for real."""

    replay_epochs = False           # `ReplayedEpochs` once RECORDED_EPOCHS are gathered
    replay_emission = False         # photon job messages answered at once (`emit`)
    steps_to_record = RECORDED_STEPS

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.recorded: list[tuple[dict, int]] = []   # (results fields, paths traced)
        self.counters.update(replayed_steps=0, recorded_paths=0, recorded_s=0.0)

    def hold_epochs(self, epochs) -> None:
        super().hold_epochs(ReplayedEpochs(epochs) if self.replay_epochs and epochs is not None else epochs)

    def _trace_photons(self, view, taken):
        if len(self.recorded) < self.steps_to_record:
            t0 = time.perf_counter()
            epochs, self.epochs = self.epochs, None      # the record keeps the step's deposits
            try:
                out = super()._trace_photons(view, taken)
            finally:
                self.epochs = epochs
            self.counters["recorded_s"] += time.perf_counter() - t0
            self.counters["recorded_paths"] += taken.rays
            fields = out[0].fields
            self.recorded.append((fields, taken.rays))
            if epochs is not None:
                epochs.add(fields["deposits"])
                out[0] = Out(SERVER, "results", {k: v for k, v in fields.items() if k != "deposits"})
            return out
        ids, fed = np.unique(np.concatenate([p.batch.job for p in taken.items]), return_counts=True)
        return [self._replayed(view.index, ids, fed, concat_credit(taken.items))]

    def emit(self, job_ids, rng_keys, counts, cull_box, credit: tuple) -> list[Out]:
        """With `replay_emission`, once the recorded steps are in hand, a
        photon job message is answered at once, as if its photons were
        made and traced: one results message per recorded step's worth of
        paths (the message rate a real tracer's steps give the server),
        splitting the message's credit among them."""
        if not (self.replay_emission and len(self.recorded) >= self.steps_to_record) or not len(job_ids):
            return super().emit(job_ids, rng_keys, counts, cull_box, credit)
        jobs = np.repeat(np.asarray(job_ids, np.int64), counts)
        self.counters["photons_emitted"] += len(jobs)
        step = max(self.recorded[0][1], 1)
        pieces = [_runs(jobs[i:i + step]) for i in range(0, len(jobs), step)]
        kept, shares = split_credit(*credit, [ids for ids, _fed in pieces])
        whole = self._whole_paths()
        out = []
        for i, ((ids, fed), share) in enumerate(zip(pieces, shares)):
            if i == 0:          # the rest of the message's credit comes back with the first
                share = tuple(np.concatenate([a, b]) for a, b in zip(share, kept))
            out.append(self._replayed(0, ids, fed, share, whole))
        return out

    def _whole_paths(self) -> tuple[dict, int]:
        """The recorded steps as one record of whole photon paths: all their
        deposits over all the paths they ended. A step's deposits per ray
        traced would undercount a path's (a path is several rays, and with
        direct light by shadow rays its first surface deposits nothing),
        and only the paper's format, which sends every deposit, would
        notice: its bytes per photon are the slow link's yardstick."""
        if len(self.recorded) != getattr(self, "_whole_of", None):
            fields = [f for f, _ in self.recorded]
            ends = np.sum([f["ends"] for f in fields], axis=0)
            self._whole = ({"deposits": type(fields[0]["deposits"]).concat([f["deposits"] for f in fields]),
                            "ends": ends}, int(ends.sum()))
            self._whole_of = len(self.recorded)
        return self._whole

    def _replayed(self, chunk: int, ids: np.ndarray, fed: np.ndarray, credit: tuple, record=None) -> Out:
        """The next recorded step's results (or `record`, (fields, paths)),
        relabelled to paths of jobs `ids` (`fed` paths each), every path ended."""
        fields, paths = record or self.recorded[self.counters["replayed_steps"] % len(self.recorded)]
        self.counters["replayed_steps"] += 1
        self.counters["rays_traced"] += int(fed.sum())
        keeps = getattr(self.epochs, "keeps_deposits", True)
        replayed = _relabelled(fields, paths, ids, fed, chunk, (self.queued_rays, self.queue_target()),
                               credit, with_deposits=keeps)
        if self.epochs is not None:     # gathered here, when the server asks for the epoch's sums
            deposits = replayed.pop("deposits")
            if keeps:
                self.epochs.add(deposits)
        return Out(SERVER, "results", replayed)


class ReplayedEpochs(EpochDeposits):
    """A tracer's epochs that are gathered for real until RECORDED_EPOCHS
    sums answers are recorded; then every `sums` request is answered with
    a recorded one, its rows cycled to the hit points asked about, and no
    deposit is kept. The other phases (a count, a pilot) are answered as
    usual, from whatever is held (nothing, once replaying: no pixel is
    fitted then, and it tries again at the next epoch)."""

    def __init__(self, base: EpochDeposits):
        self.__dict__.update(base.__dict__)
        self.recorded: list[dict] = []

    @property
    def keeps_deposits(self) -> bool:
        return len(self.recorded) < RECORDED_EPOCHS

    def add(self, deposits) -> None:
        if self.keeps_deposits:
            super().add(deposits)

    def reply(self, msg) -> dict:
        if msg.phase != "sums" or self.keeps_deposits:
            out = super().reply(msg)
            if msg.phase == "sums":
                hp = self._hits(msg.hits_version)
                m, phi = dense_sums(len(hp), out["m"], out["phi"], out.get("rows"))
                self.recorded.append(dict(out, m=m, phi=phi))
            return out
        rec = self.recorded[self.counters["epochs_gathered"] % len(self.recorded)]
        k = int(msg.epochs)             # a merged gather: as many epochs' sums
        self.take_held(int(msg.epoch), k)
        rows = np.arange(len(self._hits(msg.hits_version))) % max(len(rec["m"]), 1)
        self.counters["epochs_gathered"] += 1
        return dict(epoch=int(msg.epoch), phase="sums", hits_version=msg.hits_version, deposits=k * rec["deposits"],
                    chosen=0, flux=k * rec["flux"], **sparse_sums(k * rec["m"][rows], k * rec["phi"][rows]))


def _runs(jobs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ids, paths of each) of a job column whose equal ids are contiguous
    (a job message's photons, made job by job): np.unique without its sort."""
    starts = np.r_[0, np.flatnonzero(jobs[1:] != jobs[:-1]) + 1]
    return jobs[starts], np.diff(np.r_[starts, len(jobs)])


def _relabelled(fields: dict, paths: int, ids: np.ndarray, fed: np.ndarray, chunk: int, queue: tuple,
                credit: tuple, with_deposits: bool = True) -> dict:
    """A recorded step's results for a package of paths of jobs `ids`
    (`fed` paths each): deposits cycled to the package's size and spread
    over its jobs, every path ended, so all of the package's `credit`
    returned. `queue`: the tracer's (queued rays, queue target), as every
    results message says."""
    total = int(fed.sum())
    rec = fields["deposits"]
    n = int(round(len(rec) * total / max(paths, 1))) if with_deposits else 0
    rows = np.arange(n) % max(len(rec), 1)
    deposits = dataclasses.replace(rec.take(rows), job=ids[np.arange(n) % len(ids)].astype(np.int64))
    ends = np.asarray(fields["ends"]) * total // max(paths, 1)
    ends[np.argmax(ends)] += total - ends.sum()      # the wire checks: every path ended once
    return dict(chunk=chunk, ends=ends, culled=0, deposits=deposits, job_ids=ids.astype(np.int64),
                job_fed=fed.astype(np.int64), job_left=np.zeros(len(ids), np.int64), queued=queue[0],
                queue_target=queue[1], credit_job=credit[0], credit_exp=credit[1])


class ReplayTracer(TracerProcess):
    state_class = ReplayState


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(scene: str, tracers: int, seconds: float, work: str, extra=(), hosts: dict | None = None,
        wait_s: float | None = None, replay_epochs: bool = False, replay_emission: bool = False) -> dict:
    """One server and `tracers` synthetic tracers for `seconds`; returns the
    server's summary (its JSON) and the tracers' recorded rates. `wait_s`:
    how long the server may take to end (default ten times `seconds` and 5
    minutes) before it is killed and this raises. `hosts`:
    {"server": (namespace, address), "tracers": [namespace, ...]} to run
    each process in its own network namespace (harness/netns.py)
    instead of all on 127.0.0.1. `replay_epochs`: the tracers answer
    epochs past the first RECORDED_EPOCHS with recorded sums
    (`ReplayedEpochs`) instead of gathering. `replay_emission`: they
    answer photon job messages at once, without making photons
    (`ReplayState.emit`)."""
    from dosppm_core.chunks.subdivide import open_or_subdivide
    from dosppm_core.scene import builtin
    from dosppm_core.scene.soup import SceneSource
    store = open_or_subdivide(SceneSource(builtin.make(scene)), os.path.join(work, "store"), chunks=1)
    port = _free_port()
    endpoint = f"tcp://127.0.0.1:{port}"
    wrap = {"server": [], "tracers": [[] for _ in range(tracers)]}
    bind = endpoint
    if hosts is not None:
        endpoint, bind = f"tcp://{hosts['server'][1]}:{port}", f"tcp://0.0.0.0:{port}"
        wrap = {"server": ["ip", "netns", "exec", hosts["server"][0]],
                "tracers": [["ip", "netns", "exec", ns] for ns in hosts["tracers"][:tracers]]}
    out = os.path.join(work, f"replay-{time.monotonic_ns()}.exr")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [ROOT, os.environ.get("PYTHONPATH")])))
    server = subprocess.Popen([*wrap["server"], sys.executable, *os.environ.get("DOSPPM_REPLAY_PROFILE", "").split(),
                               "-m", "services.cli", "server", store.path, "--bind", bind,
                               "--time", str(seconds), "--min-tracers", str(tracers), "--out", out,
                               "--http", "off", "--quiet", *extra], env=env)
    procs = [subprocess.Popen([*w, sys.executable, "-m", "harness.replay", "--tracer", endpoint,
                               "--store", store.path, *(["--replay-epochs"] if replay_epochs else []),
                               *(["--replay-emission"] if replay_emission else [])],
                              env=env, stdout=subprocess.PIPE, text=True)
             for w in wrap["tracers"]]
    counters = _awaited(server, procs, seconds * 10 + 300 if wait_s is None else wait_s)
    if server.returncode != 0:
        raise RuntimeError(f"replay: the server exited with status {server.returncode}")
    with open(os.path.splitext(out)[0] + ".json", encoding="utf-8") as f:
        return dict(json.load(f), replay_tracers=counters)


def _awaited(server: subprocess.Popen, procs: list, wait_s: float) -> list[dict]:
    """The synthetic tracers' counters once the server has ended. Whatever
    happens meanwhile (a server that never ends, an interrupt), no process
    outlives this: a replay server that hung once ran on for 1.5 h after
    its harness gave up, holding a core of a shared machine."""
    try:
        try:
            server.wait(timeout=wait_s)
        except subprocess.TimeoutExpired:
            raise RuntimeError(f"replay: the server did not end within {wait_s:.0f} s; killed") from None
        # Each synthetic tracer prints its counters as it ends.
        return [json.loads(p.communicate(timeout=30)[0] or "{}") for p in procs]
    finally:
        for p in (server, *procs):
            if p.poll() is None:
                p.kill()
                p.wait()


def tracer_rate(scene: str, photons: int = 400_000) -> float:
    """Photon paths per second one tracer thread traces on this machine:
    the library's photon pass on `scene`, one thread, alone (the recorded
    steps of a replay share the cores with the server, so their rate is
    not the tracer's)."""
    from dosppm_core.modes.sppm import Renderer
    from dosppm_core.scene import builtin
    from dosppm_core.settings import RenderSettings
    from harness.bench import _photon_rays
    import numba
    before = numba.get_num_threads()
    numba.set_num_threads(1)        # the kernels' parallel loops too, not only Embree's
    r = Renderer(builtin.make(scene), RenderSettings(threads=1, photons_per_iteration=50_000))
    try:
        r.run_iteration()                               # compile, fit the radii
        t0 = time.perf_counter()
        _photon_rays(r, photons, 10_000)
        return photons / (time.perf_counter() - t0)
    finally:
        r.close()
        numba.set_num_threads(before)


def figures(s: dict, per_core: float) -> dict:
    """Photons per server CPU-second, CPU per photon and per message, where
    it goes, bytes per photon on the wire, and how many tracer threads of
    `per_core` photon paths/s that feeds, from a server summary of a
    replayed render. CPU and bytes count from the render's start (the
    summary's `render_costs`): loading the store and waiting for tracers
    are no cost of photons, and weigh more the shorter the run."""
    c, r = s["counters"], s["render_costs"]
    photons, secs = c["photons_committed"], s["seconds"]
    emitted, cpu = max(c["photons_emitted"], 1), max(r["cpu_s"], 1e-9)
    server_rate = photons / cpu                      # photons per server CPU-second
    return {"seconds": secs, "photons": photons, "photons_per_s": photons / secs,
            "steady_photons_per_s": steady_rate(s),
            "server_cpu_s": cpu, "server_cpu_whole_process_s": s.get("cpu_s", 0.0),
            "server_cpu_load": cpu / secs, "photons_per_server_cpu_s": server_rate,
            "server_cpu_us_per_photon": 1e6 * cpu / max(photons, 1),
            "results_messages": c["results"], "server_cpu_ms_per_message": 1e3 * cpu / max(c["results"], 1),
            "deposits_per_message": c["deposits_received"] / max(c["results"], 1),
            "bytes_in_per_photon": r["bytes_in"] / emitted, "bytes_out_per_photon": r["bytes_out"] / emitted,
            # By message type, over the whole process (start-up's few messages in it).
            "bytes_in_per_photon_by_type": {t: b / emitted for t, b in s.get("bytes_in_by_type", {}).items()},
            "bytes_out_per_photon_by_type": {t: b / emitted for t, b in s.get("bytes_out_by_type", {}).items()},
            "update_s": s.get("update_seconds", 0.0), "update_share_of_cpu": s.get("update_seconds", 0.0) / cpu,
            **cpu_shares(r, cpu),
            "tracer_photons_per_core_s": per_core,
            # Gathering at the tracers: the most epochs one gather merged (1: none).
            "epochs_merged_most": c.get("epochs_merged_most", 1),
            "tracer_cores_per_server_core": server_rate / max(per_core, 1e-9)}


def steady_rate(s: dict) -> float:
    """Photons per second once past the start (the synthetic tracers' real
    steps, the first epochs gathered for real): the median of the status
    history's rates (photons emitted, over 5 s windows) in the run's
    second half, or the whole run's rate without a history. Every photon
    emitted is applied by the end (`photons_committed`)."""
    h = s.get("history") or {}
    half = [r for t, r in zip(h.get("t", []), h.get("photons_per_s", [])) if t >= s["seconds"] / 2]
    return float(np.median(half)) if half else s["counters"]["photons_committed"] / s["seconds"]


def tracer_gather(s: dict) -> dict:
    """The tracers' side of the gather at the tracers: seconds they spent
    gathering epochs, per photon applied (0 when the server gathers)."""
    gather_s = sum((t or {}).get("epoch_gather_s", 0.0) for t in s.get("replay_tracers", []))
    return {"tracer_gather_us_per_photon": 1e6 * gather_s / max(s["counters"]["photons_committed"], 1)}


def cpu_shares(r: dict, cpu: float) -> dict:
    """The server's CPU by part (services/server/costs.py), as shares of
    `cpu`. The loop's thread holds making photon jobs, held deposits and
    the rest (decoding, accounting, sending); besides it the statistics
    thread, and other threads: the statistics kernels' parallel workers
    and zmq's I/O. Not clamped: a negative rest would be a part counted
    twice."""
    loop, job, held, stats = r["loop_cpu_s"], r["job_making_cpu_s"], r["held_cpu_s"], r["statistics_cpu_s"]
    return {"loop_share_of_cpu": loop / cpu, "job_making_share": job / cpu, "held_share": held / cpu,
            "loop_other_share": (loop - job - held) / cpu, "statistics_share": stats / cpu,
            "other_threads_share": (cpu - loop - stats) / cpu}


def _tracer_main(args) -> int:
    # A server behind a saturated link may exit before its shutdown gets
    # through (benchmarks/slow_link.py): give up after REPLAY_RETRY_S of
    # silence, not a worker's minute, and still report.
    ReplayState.replay_epochs = bool(args.replay_epochs)
    ReplayState.replay_emission = bool(args.replay_emission)
    if args.replay_emission:
        ReplayState.steps_to_record = RECORDED_STEPS_EMISSION
    tp = ReplayTracer(TracerOptions(args.tracer, store=args.store, threads=1, tracer_id=f"replay-{os.getpid()}",
                                    connect_timeout_s=REPLAY_RETRY_S))
    try:
        tp.run()
    except TracerError as e:
        print(f"replay tracer: {e}", file=sys.stderr)
    state = getattr(tp, "state", None)
    counters = state and dict(state.counters, **({} if state.epochs is None else
                                                 {"epoch_" + k: v for k, v in state.epochs.counters.items()}))
    print(json.dumps(counters))
    return 0


def report(res: dict) -> str:
    r = res["replay"]
    return "\n".join([
        f"Replay: {res['scene']}, one server and {res['tracers']} synthetic tracers, {res['seconds']:.0f} s a run, "
        f"medians of {r['repeats']}. Server CPU and bytes from the render's start (start-up left out).", "",
        "| figure | value |", "|---|---|",
        f"| photons applied per second of server CPU | {r['photons_per_server_cpu_s']:,.0f} |",
        f"| server CPU per photon applied (microseconds) | {r['server_cpu_us_per_photon']:.2f} |",
        f"| server CPU, render / whole process incl. start-up (s) "
        f"| {r['server_cpu_s']:.2f} / {r['server_cpu_whole_process_s']:.2f} |",
        f"| server CPU per results message (ms) | {r['server_cpu_ms_per_message']:.1f} |",
        f"| deposits per results message | {r['deposits_per_message']:,.0f} |",
        f"| bytes per photon emitted, tracers to server | {r['bytes_in_per_photon']:.1f} |",
        f"| bytes per photon emitted, server to tracers | {r['bytes_out_per_photon']:.1f} |",
        f"| the message loop's thread, share of server CPU | {r['loop_share_of_cpu']:.0%} |",
        f"| ... making photon jobs (emission, routing, encoding) | {r['job_making_share']:.0%} |",
        f"| ... held deposits (adding, re-culling, releasing) | {r['held_share']:.0%} |",
        f"| ... the rest of the loop (decoding, accounting, sending) | {r['loop_other_share']:.0%} |",
        f"| statistics updates (their thread), share | {r['statistics_share']:.0%} |",
        f"| other threads (the statistics kernels' workers, zmq's I/O), share "
        f"| {r['other_threads_share']:.0%} |",
        f"| one tracer thread, photon paths/s (alone, same scene) | {r['tracer_photons_per_core_s']:,.0f} |",
        *([f"| tracers' gather per photon applied (microseconds, gather at tracers) "
           f"| {r['tracer_gather_us_per_photon']:.3f} |"] if r.get("tracer_gather_us_per_photon") else []),
        f"| **tracer cores one server core feeds** | **{r['tracer_cores_per_server_core']:.1f}** |",
        "| ... in the paper's CPU server / GPU server | 12.4 / 105 |"])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tracer", help=argparse.SUPPRESS)      # internal: be one synthetic tracer
    p.add_argument("--store", help=argparse.SUPPRESS)
    p.add_argument("--replay-epochs", action="store_true",
                   help="gathering at the tracers, answer epochs with recorded sums after the first "
                        f"{RECORDED_EPOCHS} (the tracers' gather then costs nothing)")
    p.add_argument("--replay-emission", action="store_true",
                   help="answer photon job messages at once, without making their photons, once the recorded "
                        "steps are in hand (the tracers' emission then costs nothing)")
    p.add_argument("--scene", default="cornell-glass")
    p.add_argument("--tracers", type=int, default=2)
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--gather-at", choices=("server", "tracers"), default="server",
                   help="where photons are gathered (the server's --gather-at)")
    p.add_argument("--hit-point-stride", type=int, default=None,
                   help="the server's --hit-point-stride (default: its own; 1: every eye iteration installs)")
    p.add_argument("--server-arg", action="append", default=[], metavar="ARG",
                   help="one more argument for the server, as in --server-arg=--photon-batch=4000000 (repeatable)")
    p.add_argument("--json", help="write the runs, with provenance, here")
    args = p.parse_args(argv)
    if args.tracer:
        return _tracer_main(args)
    from harness.provenance import median_of, write_results
    runs = []
    with tempfile.TemporaryDirectory(prefix="dosppm-replay-") as work:
        for _ in range(args.repeats):       # alternated: drift on a shared machine hits both alike
            per_core = tracer_rate(args.scene)
            extra = ("--gather-at", args.gather_at) + (
                () if args.hit_point_stride is None else ("--hit-point-stride", str(args.hit_point_stride))) + tuple(
                args.server_arg)
            s = run(args.scene, args.tracers, args.seconds, work, extra, replay_epochs=args.replay_epochs,
                    replay_emission=args.replay_emission)
            runs.append(dict(figures(s, per_core), **tracer_gather(s)))
    res = {"scene": args.scene, "tracers": args.tracers, "seconds": args.seconds, "gather_at": args.gather_at,
           "hit_point_stride": args.hit_point_stride, "server_args": args.server_arg,
           "replay_epochs": args.replay_epochs, "replay_emission": args.replay_emission,
           "replay": median_of(runs)}
    print(report(res))
    if args.json:
        write_results(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
