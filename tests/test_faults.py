"""Tracer failures on a real cluster (a server and three tracer processes
over tcp on loopback): a tracer killed with SIGKILL, and one hung with
SIGSTOP, mid-render. The server detects each within its --tracer-timeout,
reassigns the chunks, re-emits the jobs in flight, and the render
completes with no photon lost and none counted twice, by the server's own
accounting and by its ledger re-traced in this process
(services/ledger.py), its image agreeing within noise with failure-free
renders."""
from __future__ import annotations

import json
import signal
import subprocess
import time
import urllib.request

import pytest

from dosppm_core.chunks.store import ChunkStore
from dosppm_core.film import read_exr
from services import ledger
from services.server import checkpoint
from tests.helpers import figures
from tests.helpers.cli import free_port, run_dosppm, start_dosppm
from tests.helpers.cluster import assert_same_within_noise

pytestmark = pytest.mark.slow   # a server and three tracer processes per render
PHOTONS = 1_500_000
TIMEOUT_S = 3.0


class Cluster:
    """`dosppm server` and three `dosppm worker` processes."""

    def __init__(self, tmp, seed: int, workers: int = 3, server_args: tuple = ()):
        self.tmp, self.port, self.http, self.seed = tmp, free_port(), free_port(), seed
        self.n, self.server_args = workers, tuple(server_args)
        self.server = self.start_server()
        self.workers = [start_dosppm(
            "worker", "--server", f"tcp://127.0.0.1:{self.port}", "--threads", "1", "--id", f"w{i}",
            "--cache-dir", str(tmp / f"cache{i}"), "--quiet",
            stderr=open(tmp / f"worker{i}.log", "w")) for i in range(workers)]

    def start_server(self, *extra: str, log: str = "server.log"):
        cmd = ["server", "cornell-caustic", "--width", "64",
               "--height", "64", "--chunks", "4", "--bind", f"tcp://127.0.0.1:{self.port}",
               "--http", f"127.0.0.1:{self.http}", "--min-tracers", str(self.n), "--photons", str(PHOTONS),
               "--photons-per-iteration", "40000", "--min-photon-jobs", "64", "--seed", str(self.seed),
               # 1,024-photon jobs (not the service's 4,096): the render
               # then lasts long enough for a hung tracer to wake and rejoin.
               "--photons-per-job", "1024",
               "--tracer-timeout", str(TIMEOUT_S), "--threads", "1", "--out", str(self.tmp / "img.exr"),
               "--store-cache", str(self.tmp / "stores"), "--checkpoint", str(self.tmp / "ckpt"),
               "--checkpoint-interval", "1", "--ledger", str(self.tmp / "render.ledger"), "--quiet",
               *self.server_args, *extra]
        return start_dosppm(*cmd, stderr=open(self.tmp / log, "w"))

    def status(self) -> dict:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{self.http}/status", timeout=2) as r:
                return json.load(r)
        except OSError:
            return {}

    def wait_for(self, predicate, timeout_s=120.0) -> dict:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and self.server.poll() is None:
            st = self.status()
            if st and predicate(st):
                return st
            time.sleep(0.2)
        raise AssertionError(f"condition not reached; last status {self.status()}\n{self.logs()}")

    def finish(self, timeout_s=180.0):
        code = self.server.wait(timeout_s)
        assert code == 0, self.logs()
        for w in self.workers:
            if w.poll() is None:
                try:
                    w.wait(20)
                except subprocess.TimeoutExpired:
                    w.kill()
        with open(self.tmp / "img.json", encoding="utf-8") as f:
            return read_exr(str(self.tmp / "img.exr"))[0], json.load(f)

    def logs(self) -> str:
        return "\n".join(f"--- {p.name}\n{p.read_text()[-1500:]}" for p in sorted(self.tmp.glob("*.log")))

    def close(self):
        for p in (self.server, *self.workers):
            if p.poll() is None:
                p.send_signal(signal.SIGCONT)
                p.kill()
                p.wait()


def _render(tmp, seed, fault=None, workers: int = 3, server_args: tuple = ()):
    c = Cluster(tmp, seed, workers, server_args)
    try:
        if fault:
            fault(c)
        return c.finish()
    finally:
        c.close()


@pytest.fixture(scope="module")
def failure_free(tmp_path_factory):
    """Failure-free renders with the test's seed and another (the noise)."""
    return {seed: _render(tmp_path_factory.mktemp(f"free{seed}"), seed)[0] for seed in (5, 9)}


def _mid_render(c: Cluster) -> None:
    c.wait_for(lambda st: st.get("photons_committed", 0) > 0 and len(st.get("tracers", [])) == 3)


def _assert_ledger(tmp) -> None:
    """Exactly once, from outside the server: the jobs its ledger says it
    applied, re-traced in this process, give its totals (services/ledger.py)."""
    (store,) = [d for d in (tmp / "stores").iterdir() if (d / "manifest.msgpack").exists()]
    problems = ledger.check(ChunkStore.open(str(store)), ledger.read(str(tmp / "render.ledger")))
    assert problems == [], problems


def _assert_exactly_once(summary: dict, tmp) -> None:
    _assert_ledger(tmp)
    k = summary["counters"]
    assert k["tracers_evicted"] >= 1 and k["jobs_discarded"] > 0
    lost = k["photons_emitted"] - k["photons_discarded"] - k["photons_completed"]
    assert lost == 0, k
    assert k["photons_completed"] == k["photons_committed"] == summary["photons_applied"]
    assert k["over_credited_jobs"] == 0, k
    assert summary["jobs_in_flight"] == 0


def test_a_tracer_killed_mid_render(tmp_path, failure_free):
    # evicted=1 only if the whole test passes (eviction in time, exact, the
    # image within noise); a failure records 0 (tests/helpers/figures.py).
    with figures.outcome("tracer killed (SIGKILL)", "evicted", timeout_s=TIMEOUT_S) as fig:
        def kill(c: Cluster):
            _mid_render(c)
            t0 = time.monotonic()
            c.workers[1].send_signal(signal.SIGKILL)
            st = c.wait_for(lambda st: st["counters"]["tracers_evicted"] >= 1)
            detected = time.monotonic() - t0
            fig["detected_s"] = round(detected, 2)
            assert detected < TIMEOUT_S + 3.0, f"detected after {detected:.1f} s"
            assert {t["id"] for t in st["tracers"]} == {"w0", "w2"}
            assert sorted(k for t in st["tracers"] for k in t["chunks"]) == [0, 1, 2, 3]
        img, summary = _render(tmp_path, 5, kill)
        _assert_exactly_once(summary, tmp_path)
        assert_same_within_noise(img, failure_free[5], failure_free[9])


def test_a_hung_tracer_is_dropped_and_rejoins_when_it_wakes(tmp_path, failure_free):
    def hang(c: Cluster):
        _mid_render(c)
        c.workers[2].send_signal(signal.SIGSTOP)
        c.wait_for(lambda st: st["counters"]["tracers_evicted"] >= 1)
        c.workers[2].send_signal(signal.SIGCONT)
        # Awake again, it learns it was dropped, registers and gets chunks.
        c.wait_for(lambda st: any(t["id"] == "w2" and t["chunks"] for t in st["tracers"]), 30)
    with figures.outcome("tracer hung (SIGSTOP), then woken", "rejoined", timeout_s=TIMEOUT_S):
        img, summary = _render(tmp_path, 5, hang)
        _assert_exactly_once(summary, tmp_path)
        assert_same_within_noise(img, failure_free[5], failure_free[9])


def _kill_and_resume(saved: dict):
    """A `crash` for `_render`: SIGKILL the server once a quarter of the
    photons are committed and a checkpoint is written, keep the checkpoint
    in `saved`, and start the server again with --resume; the three
    tracers find it by themselves."""
    def crash(c: Cluster):
        c.wait_for(lambda st: st.get("photons_committed", 0) > PHOTONS // 4)
        c.wait_for(lambda st: (c.tmp / "ckpt" / "checkpoint.msgpack").exists())
        c.server.send_signal(signal.SIGKILL)
        c.server.wait(10)
        saved.update(checkpoint.read(str(c.tmp / "ckpt")))
        c.server = c.start_server("--resume", str(c.tmp / "ckpt"), log="server2.log")
        c.wait_for(lambda st: len(st.get("tracers", [])) == 3, 60)
    return crash


def _assert_resumed(summary: dict, saved: dict, tmp_path) -> None:
    """The image holds the checkpoint's photons and the resumed server's,
    each counted once, and the ledger (up to the checkpoint, then the
    second server's) re-traces to the server's totals."""
    assert summary["photons_in_image"] >= PHOTONS
    assert summary["photons_in_image"] == saved["photons_emitted"] + summary["photons_applied"]
    k = summary["counters"]
    assert k["photons_emitted"] - k["photons_discarded"] == k["photons_completed"] == k["photons_committed"]
    _assert_ledger(tmp_path)


def test_the_server_killed_and_resumed_from_its_checkpoint(tmp_path, failure_free):
    """SIGKILL the server mid-render and start it again with --resume: the
    tracers find it again by themselves, and the render goes on from the
    checkpoint to the same total photon count."""
    saved = {}
    with figures.outcome("server killed (SIGKILL), --resume", "resumed", timeout_s=TIMEOUT_S) as fig:
        img, summary = _render(tmp_path, 5, _kill_and_resume(saved))
        fig.update(photons_before_kill=saved["photons_emitted"], photons_in_image=summary["photons_in_image"])
        assert 0 < saved["photons_emitted"] < PHOTONS
        _assert_resumed(summary, saved, tmp_path)
        assert_same_within_noise(img, failure_free[5], failure_free[9])


@pytest.mark.parametrize("damage, words", [
    (lambda p: p.write_bytes(p.read_bytes()[:200]), ["corrupt or truncated"]),
    (lambda p: p.write_bytes(p.read_bytes().replace(b"dosppm-checkpoint", b"dosppm-checkpoinX")),
     ["'format'", "not a dosppm checkpoint"]),
])
def test_a_corrupt_or_foreign_checkpoint_is_refused(tmp_path, damage, words):
    run = ["render", "cornell-box", "--width", "16", "--height", "16",
           "--tracers", "1", "--time", "1", "--http", "off", "--store-cache", str(tmp_path / "stores"),
           "--quiet"]
    first = run_dosppm(*run, "--out", tmp_path / "a.exr", "--checkpoint", tmp_path / "ck")
    assert first.returncode == 0, first.stderr
    # Another scene (another store key) is refused by name.
    other = run_dosppm(run[0], "cornell-caustic", *run[2:], "--out", tmp_path / "b.exr",
                       "--resume", tmp_path / "ck")
    assert other.returncode == 2 and "another scene" in other.stderr
    damage(tmp_path / "ck" / "checkpoint.msgpack")
    bad = run_dosppm(*run, "--out", tmp_path / "c.exr", "--resume", tmp_path / "ck")
    lines = bad.stderr.strip().splitlines()
    assert bad.returncode == 2 and len(lines) == 1, bad.stderr
    assert all(w in lines[0] for w in words), lines[0]
    assert not (tmp_path / "c.exr").exists()


def test_a_tracer_added_mid_render_gets_work(tmp_path, failure_free):
    """Two tracers start the render; a third joins while it runs, is given
    chunks by the new round-robin table and traces; nothing is lost."""
    def join(c: Cluster):
        # Once photons flow, not once the first batch is committed: that
        # is 1M of the 1.5M photons, and a tracer starting on a loaded
        # machine could find the render over.
        c.wait_for(lambda st: st.get("photons_emitted", 0) > 0)
        c.workers.append(start_dosppm(
            "worker", "--server", f"tcp://127.0.0.1:{c.port}", "--threads", "1", "--id", "late",
            "--cache-dir", str(c.tmp / "late"), "--quiet", stderr=open(c.tmp / "late.log", "w")))
        c.wait_for(lambda st: any(t["id"] == "late" and t["chunks"] and t["results"] > 0
                                  for t in st["tracers"]), 60)
    c_workers = 2
    img, summary = _render(tmp_path, 5, join, workers=c_workers)
    k = summary["counters"]
    assert {t["id"] for t in summary["tracers"]} == {"w0", "w1", "late"}
    assert k["photons_emitted"] - k["photons_discarded"] == k["photons_completed"] == k["photons_committed"]
    assert k["over_credited_jobs"] == 0 and k["tracers_evicted"] == 0
    _assert_ledger(tmp_path)
    assert_same_within_noise(img, failure_free[5], failure_free[9])


TRACERS_GATHER = ("--gather-at", "tracers", "--photon-batch", "200000")   # several epochs a render


def test_a_tracer_killed_mid_epoch_with_the_gather_at_the_tracers(tmp_path, failure_free):
    """Issue 32: with the tracers holding deposits by epoch, a killed
    tracer costs the open epochs (discarded, their jobs made again) and
    nothing else: exactly once by the counters and the ledger."""
    def kill(c: Cluster):
        _mid_render(c)
        c.workers[1].send_signal(signal.SIGKILL)
        c.wait_for(lambda st: st["counters"]["tracers_evicted"] >= 1)
    img, summary = _render(tmp_path, 5, kill, server_args=TRACERS_GATHER)
    _assert_exactly_once(summary, tmp_path)
    assert_same_within_noise(img, failure_free[5], failure_free[9])


def test_the_server_killed_mid_epoch_and_resumed_with_the_gather_at_the_tracers(tmp_path, failure_free):
    saved = {}
    img, summary = _render(tmp_path, 5, _kill_and_resume(saved), server_args=TRACERS_GATHER)
    _assert_resumed(summary, saved, tmp_path)
    assert_same_within_noise(img, failure_free[5], failure_free[9])
