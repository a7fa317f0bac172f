"""Network faults between real hosts: a server and two tracers, each in its
own Linux network namespace on a private bridge (tests/helpers/netns.py;
RECIPES.md, "Several hosts on one machine"), the tracers fetching their
chunks over the wire and advertising their own address. While the render
runs (a photon limit, so a slowed render emits as many photons; those of
discarded jobs count towards it too):

- a tracer's cable is pulled for 2 s, less than --tracer-timeout: the
  render stalls and goes on, nobody is evicted;
- a tracer's cable is pulled for longer than --tracer-timeout, until the
  render is over: the tracer is evicted, the other one renders on alone
  and finishes; plugged in again, the cut-off tracer finds no server and
  gives up after its --retry;
- a tracer's cable is pulled for 8 s, more than --tracer-timeout, and
  plugged in again mid-render: the tracer rejoins, gets chunks and helps
  finish the render;
- 5% of the packets a tracer receives are dropped (iptables): the render
  is slower.

In every case the server (and every tracer that stayed connected) exits
0, the server's accounting (OUT.json) is exact (emitted - discarded =
completed = committed = applied, nothing over-counted, no job left in
flight), its ledger re-traced in the test's process gives its totals
(services/ledger.py: exactly once, checked from outside), and the image is finite, not black, and its mean luminance
within 3% of a fault-free render's with the same seed (not closer: faults
change how many eye iterations a photon limit gets).

Needs root, Linux and `ip` (iproute2); the packet-loss test also needs
`iptables` with the `statistic` match. Skipped otherwise.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

from dosppm_core.chunks.store import ChunkStore
from dosppm_core.film import read_exr
from services import ledger
from tests.helpers import figures, netns
from tests.helpers.cli import DOSPPM
from tests.helpers.netns import Procs

pytestmark = [pytest.mark.netns, pytest.mark.slow]
PHOTONS = 1_500_000
PHOTONS_REJOIN = 4_000_000   # still rendering when the cable is back
SEED = 11
ZMQ_PORT, HTTP_PORT, PEER_PORT = 5555, 8080, 5600
SERVER_TIMEOUT_S = 50     # from the server's start to its exit, fault included
# The --tracer-timeout each test runs at, recorded beside its figures.
SHORT_CUT_TIMEOUT_S, CUT_TIMEOUT_S, LOSS_TIMEOUT_S = 6, 3, 10
WORKER_TIMEOUT_S = 20     # after the server has exited

# A unique name prefix per test run and a /24 of its own (test_netns.py
# uses 10.213.x.0/24): parallel or leftover runs cannot clash.
_PID = os.getpid()
SUBNET = f"10.214.{_PID % 250 + 1}"
HOSTS = {"server": f"{SUBNET}.1", "t1": f"{SUBNET}.11", "t2": f"{SUBNET}.12"}
_LANS = iter(range(1000))

# Runs in the server's host (which no fault touches): polls the status
# page and appends what the tests look at, one JSON line a poll.
HISTORY_POLLER = r"""
import json, sys, time, urllib.request
url, out, deadline = sys.argv[1], sys.argv[2], time.time() + float(sys.argv[3])
while time.time() < deadline:
    try:
        with urllib.request.urlopen(url, timeout=2) as r:
            st = json.loads(r.read())
        rec = {"t": time.time(), "committed": st.get("photons_committed", 0),
               "counters": st.get("counters", {}),
               "tracers": [{k: t.get(k) for k in ("id", "chunks", "results", "endpoint")}
                           for t in st.get("tracers", [])]}
        with open(out, "a") as f:
            f.write(json.dumps(rec) + "\n")
    except Exception:
        pass
    time.sleep(0.2)
"""


class Lan:
    """The hosts of one test ({host: (namespace, address)}) and the
    namespace of the bridge they hang on."""

    def __init__(self, prefix, hosts):
        self.hosts, self.bridge_ns = hosts, f"{prefix}-lan"

    def link(self, host: str, state: str) -> None:
        """Plug (`up`) or pull (`down`) the cable of `host` at the bridge."""
        netns.ip("-n", self.bridge_ns, "link", "set", f"v-{host}", state)


@pytest.fixture
def lan():
    prefix = f"dpf-{_PID}-{next(_LANS)}"
    with netns.lan(prefix, HOSTS) as hosts:
        yield Lan(prefix, hosts)


class Render:
    """One render on the LAN: `dosppm server` on host `server`, `dosppm
    worker` on t1 and t2 (chunks fetched over the wire, peers bound to
    0.0.0.0, --advertise auto), and a status poller on the server's host
    (which no fault touches)."""

    def __init__(self, hosts, folder, tracer_timeout_s: float, photons: int = PHOTONS, retry_s: float = 60):
        self.hosts, self.folder = hosts, folder
        folder.mkdir()
        self.out, self.history_file = folder / "out.exr", folder / "status.jsonl"
        self.procs = Procs(folder)
        server_ns, server_ip = hosts["server"]
        py = DOSPPM
        env = {"DOSPPM_LOG_LEVEL": "info", "PYTHONUNBUFFERED": "1"}
        self.t0 = time.monotonic()
        self.procs.start("server", server_ns, py + [
            "server", "cornell-caustic", "--bind", f"tcp://{server_ip}:{ZMQ_PORT}",
            "--http", f"{server_ip}:{HTTP_PORT}", "--min-tracers", "2", "--photons", str(photons),
            "--min-photon-jobs", "64", "--seed", str(SEED), "--tracer-timeout", str(tracer_timeout_s),
            # 1,024-photon jobs (not the service's 4,096), as the faults
            # were timed: at 4,096 the lossy render took 3.9 s, and the
            # server's shutdown did not reach the lossy tracer before it exited.
            "--photons-per-job", "1024",
            "--out", str(self.out), "--width", "64", "--height", "64", "--chunks", "4",
            "--threads", "1", "--store-cache", str(folder / "store-cache"), "--checkpoint-interval", "0",
            "--ledger", str(folder / "render.ledger"), "--quiet"], env)
        for h in ("t1", "t2"):
            self.procs.start(h, hosts[h][0], py + [
                "worker", "--server", f"tcp://{server_ip}:{ZMQ_PORT}", "--bind", f"tcp://0.0.0.0:{PEER_PORT}",
                "--advertise", "auto", "--cache-dir", str(folder / f"cache-{h}"), "--threads", "1",
                "--id", f"tracer-{h}", "--retry", str(retry_s), "--quiet"], env)
        self.procs.start("poller", server_ns, [sys.executable, "-c", HISTORY_POLLER,
                                               f"http://{server_ip}:{HTTP_PORT}/status",
                                               str(self.history_file), str(SERVER_TIMEOUT_S + 10)])

    def since_start(self) -> float:
        return time.monotonic() - self.t0

    def history(self) -> list[dict]:
        try:
            lines = self.history_file.read_text().splitlines()
        except OSError:
            return []
        out = []
        for line in lines:
            try:
                out.append(json.loads(line))
            except ValueError:          # a line being written
                pass
        return out

    def last(self) -> dict:
        h = self.history()
        return h[-1] if h else {}

    def wait_for(self, what: str, predicate, timeout_s: float) -> dict:
        """The first status polled from now on that satisfies `predicate`."""
        deadline, seen = time.monotonic() + timeout_s, len(self.history())
        while time.monotonic() < deadline:
            h = self.history()
            for rec in h[seen:]:
                if predicate(rec):
                    rec["since_start"] = self.since_start() - (time.time() - rec["t"])
                    return rec
            seen = len(h)
            if self.procs.procs["server"].poll() is not None:
                break
            time.sleep(0.1)
        raise AssertionError(f"{what}: not seen within {timeout_s} s (server exit {self.server_exit()}); "
                             f"last status {self.last()}\n{self.procs.tails()}")

    def mid_render(self) -> dict:
        """Both tracers serving chunks, photons being committed."""
        return self.wait_for("both tracers rendering", lambda r: r["committed"] > 0 and len(r["tracers"]) == 2
                             and all(t["chunks"] for t in r["tracers"]), 40)

    def server_exit(self, timeout_s: float = 0.0):
        """The server's exit status, waiting up to `timeout_s`; None while it runs."""
        return self.procs.wait("server", timeout_s) if timeout_s > 0 else self.procs.procs["server"].poll()

    def finish(self, expect=None) -> dict:
        """Wait for every process (killing what is left at the end) and check
        the exit statuses; the summary (OUT.json), the image, the history."""
        expect = expect or {"server": 0, "t1": 0, "t2": 0}
        try:
            rc = {"server": self.server_exit(SERVER_TIMEOUT_S - self.since_start())}
            deadline = time.monotonic() + WORKER_TIMEOUT_S
            for h in ("t1", "t2"):
                rc[h] = self.procs.wait(h, deadline - time.monotonic())
        finally:
            self.procs.kill_all()
        self.tails = self.procs.tails()
        assert rc == expect, f"exit statuses {rc}, expected {expect} (None: still running)\n{self.tails}"
        summary = json.loads(self.out.with_suffix(".json").read_text())
        img, _ = read_exr(str(self.out))
        return {"summary": summary, "img": img, "history": self.history(), "tails": self.tails,
                "ledger": ledger.read(str(self.folder / "render.ledger")),
                "store": next(d for d in (self.folder / "store-cache").iterdir()
                              if (d / "manifest.msgpack").exists()),
                "logs": {n: self.log(n) for n in ("server", "t1", "t2")}}

    def log(self, name: str) -> str:
        return self.procs.err(name, chars=10**6)

    def close(self):
        self.procs.kill_all()


def _render(hosts, folder, tracer_timeout_s, fault=None, expect=None, **kw) -> dict:
    r = Render(hosts, folder, tracer_timeout_s, **kw)
    try:
        if fault:
            fault(r)
        res = r.finish(expect)
    finally:
        r.close()
    print(f"\n{folder.name}: rendered in {res['summary'].get('seconds', float('nan')):.1f} s, "
          f"counters {res['summary']['counters']}")
    return res


def _luminance(img) -> float:
    rgb = img[..., :3].reshape(-1, 3).mean(axis=0)
    return float(0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2])


def _assert_exact(res, healthy=None, photons=PHOTONS) -> None:
    s, tails = res["summary"], res["tails"]
    k = s["counters"]
    assert k["photons_emitted"] >= photons, (k, tails)   # discarded photons count towards the limit
    assert k["photons_emitted"] - k["photons_discarded"] == k["photons_completed"] == k["photons_committed"] \
        == s["photons_applied"], (k, s["photons_applied"], tails)
    assert k["over_credited_jobs"] == 0, (k, tails)
    assert s["jobs_in_flight"] == 0, (s["jobs_in_flight"], tails)
    # From outside the server: its ledger's jobs, re-traced here, give its totals.
    problems = ledger.check(ChunkStore.open(str(res["store"])), res["ledger"])
    assert problems == [], (problems, tails)
    img = res["img"]
    assert img.shape[:2] == (64, 64), img.shape
    assert np.isfinite(img).all(), "non-finite pixels"
    assert img.mean() > 0, "black image"
    if healthy is not None:
        ratio = _luminance(img) / _luminance(healthy["img"])
        print(f"mean luminance {ratio - 1:+.2%} off the fault-free render's")
        assert abs(ratio - 1) < 0.03, f"mean luminance {ratio - 1:+.2%} off the fault-free render's"


@pytest.fixture(scope="module")
def healthy(tmp_path_factory):
    """The fault-free render, after warming numba's on-disk kernel cache
    (a cold one costs each process 10-20 s of compiling)."""
    prefix = f"dpf-{_PID}-healthy"
    why = netns.netns_unavailable(prefix)
    if why:
        pytest.skip(why)
    folder = tmp_path_factory.mktemp("netns-faults")
    netns.warm_kernel_cache(folder / "warm-up")
    with netns.lan(prefix, HOSTS) as hosts:
        res = _render(hosts, folder / "healthy", 10)
    _assert_exact(res)
    assert res["summary"]["counters"]["tracers_evicted"] == 0, (res["summary"]["counters"], res["tails"])
    return res


# 2 s: TCP's retransmission back-off (0.2, 0.6, 1.4, 3.0, 6.2 s after the
# first lost segment) has the connection back about 3 s after the cut,
# before the tracer's own 5 s of silence makes it register again. A 4.5 s
# cut (under --tracer-timeout 10) makes the tracer re-register while still
# registered: welcomed again, it forgets its queues without the server
# discarding the jobs in flight, and the render stalled for good in 3 of 5
# tries; too irregular for a strict expected failure, so not tested here.
def test_a_short_link_cut_stalls_the_render_without_an_eviction(lan, tmp_path, healthy):
    # passed=1 only if every assertion holds; a failure records 0.
    with figures.outcome("cable cut 2 s (< timeout)", "passed", timeout_s=SHORT_CUT_TIMEOUT_S) as fig:
        _short_cut(lan, tmp_path, healthy, fig)


def _short_cut(lan, tmp_path, healthy, fig: dict) -> None:
    cut = {}

    def pull_the_cable(r: Render):
        r.mid_render()
        lan.link("t1", "down")
        cut["down"] = time.time()
        cut["committed_at_cut"] = r.last().get("committed")
        time.sleep(2.0)
        cut["up"] = time.time()
        lan.link("t1", "up")
        cut["server_exit_at_plug"] = r.server_exit()
    res = _render(lan.hosts, tmp_path / "short-cut", SHORT_CUT_TIMEOUT_S, pull_the_cable)
    # The stall: while the cable is out, jobs with paths at t1 cannot
    # complete (their credit is there), so completions nearly stop.
    stalled = _completion_rate(res["history"], cut["down"] + 0.5, cut["up"])
    healthy_rate = healthy["summary"]["counters"]["photons_completed"] / healthy["summary"]["seconds"]
    print(f"short cut: {cut}; completions during the cut {stalled:,.0f}/s, healthy {healthy_rate:,.0f}/s")
    fig.update(seconds=round(res["summary"]["seconds"], 2), healthy_seconds=round(healthy["summary"]["seconds"], 2),
               rate_during_cut=round(stalled / healthy_rate, 3))
    assert stalled < 0.25 * healthy_rate, (stalled, healthy_rate, res["tails"])
    _assert_exact(res, healthy)
    k = res["summary"]["counters"]
    assert k["tracers_evicted"] == 0 and k["jobs_discarded"] == 0, (k, res["tails"])
    # The cable was pulled mid-render, not after the end.
    assert cut["committed_at_cut"] < PHOTONS and cut["server_exit_at_plug"] is None, (cut, res["tails"])
    assert sorted(t["id"] for t in res["summary"]["tracers"]) == ["tracer-t1", "tracer-t2"], res["tails"]
    assert "registering again" not in res["logs"]["t1"], res["logs"]["t1"][-3000:]


def _completion_rate(history: list[dict], t0: float, t1: float) -> float:
    """Photons completed per second between wall times t0 and t1, from the
    status poller's history (about 5 polls a second)."""
    window = [(h["t"], h["counters"]["photons_completed"]) for h in history
              if t0 <= h["t"] <= t1 and "counters" in h]
    assert len(window) >= 3, f"only {len(window)} status polls during the cut"
    (ta, a), (tb, b) = window[0], window[-1]
    return (b - a) / (tb - ta)


RETRY_S = 15


def test_a_long_link_cut_evicts_the_tracer_and_the_other_finishes(lan, tmp_path, healthy):
    # evicted=1 only if every assertion holds; a failure records 0.
    with figures.outcome("cable cut past the timeout", "evicted", timeout_s=CUT_TIMEOUT_S) as fig:
        _long_cut(lan, tmp_path, healthy, fig)


def _long_cut(lan, tmp_path, healthy, fig: dict) -> None:
    seen = {}

    def pull_the_cable(r: Render):
        r.mid_render()
        lan.link("t1", "down")
        t_cut = time.monotonic()
        ev = r.wait_for("t1 evicted", lambda s: s["counters"].get("tracers_evicted", 0) >= 1, 15)
        seen["evicted_after_s"] = round(time.monotonic() - (time.time() - ev["t"]) - t_cut, 1)
        fig["evicted_after_s"] = seen["evicted_after_s"]
        seen["tracers_after_eviction"] = ev["tracers"]
        seen["committed_at_eviction"] = ev["committed"]
        # The cable stays out until the render is over (at least 8 s).
        rc = r.server_exit(SERVER_TIMEOUT_S - r.since_start())
        time.sleep(max(0.0, 8.0 - (time.monotonic() - t_cut)))
        seen["cut_s"] = round(time.monotonic() - t_cut, 1)
        seen["server_exit"] = rc
        lan.link("t1", "up")
    # t1 never hears the shutdown: silent since the cut, it gives up after --retry.
    res = _render(lan.hosts, tmp_path / "long-cut", CUT_TIMEOUT_S, pull_the_cable, retry_s=RETRY_S,
                  expect={"server": 0, "t1": 1, "t2": 0})
    # Photons t2 traced alone: committed in batches of 1M deposits, so with
    # direct light by shadow rays (half the deposits) the last batch may
    # only be committed at the end; the summary has it, the poll may not.
    seen["committed_alone"] = res["summary"]["counters"]["photons_committed"] - seen["committed_at_eviction"]
    print(f"long cut: {seen}")
    assert seen["evicted_after_s"] < 3 + 4, seen   # timeout + tick, status and poll periods
    _assert_exact(res, healthy)
    k = res["summary"]["counters"]
    assert k["tracers_evicted"] == 1 and k["jobs_discarded"] > 0 and k["photons_discarded"] > 0, (k, res["tails"])
    after = seen["tracers_after_eviction"]
    assert [t["id"] for t in after] == ["tracer-t2"] and sorted(after[0]["chunks"]) == [0, 1, 2, 3], after
    assert seen["committed_alone"] > 0, seen        # t2 rendered on alone
    assert [t["id"] for t in res["summary"]["tracers"]] == ["tracer-t2"], res["summary"]["tracers"]
    last = res["logs"]["t1"].strip().splitlines()[-1]
    assert last.startswith("dosppm: error: server tcp://"), res["logs"]["t1"][-3000:]


class RejoinFailed(AssertionError):
    """The cut-off tracer did not come back and help finish the render."""


# A cut of 7-10 s used to leave the tracer out for good: its registers, or
# the server's welcome, jobs and peers' portal packages, were queued in TCP
# connections libzmq replaces after its 10 s heartbeat timeout, and were
# lost without an error. Now a tracer that goes 5 s without hearing the
# server opens a new connection and registers again (its jobs in flight are
# re-emitted); a lost welcome is resent when heartbeats do not echo it; job
# messages an idle tracer does not acknowledge are re-emitted after 4 s;
# and jobs untouched for 4 s while every tracer is idle are re-emitted
# (the 30 s watchdog stays as the last resort). 12 of 12 runs passed.


# DOSPPM_REJOIN_RUNS=N runs it N times (benchmarks/reliability.sh), for the
# figure "rejoined in k of N runs".
@pytest.mark.parametrize("run", range(int(os.environ.get("DOSPPM_REJOIN_RUNS", "1"))))
def test_a_cut_off_tracer_rejoins_once_the_link_is_back(lan, tmp_path, healthy, run):
    # rejoined=1 only if every assertion holds; any failure records 0.
    with figures.outcome("cable cut 8 s, then back", "rejoined", timeout_s=CUT_TIMEOUT_S):
        _rejoin(lan, tmp_path, healthy)


def _rejoin(lan, tmp_path, healthy) -> None:
    r = Render(lan.hosts, tmp_path / "rejoin", CUT_TIMEOUT_S, photons=PHOTONS_REJOIN)
    try:
        r.mid_render()
        lan.link("t1", "down")
        t_cut = time.monotonic()
        ev = r.wait_for("t1 evicted", lambda s: s["counters"].get("tracers_evicted", 0) >= 1, 15)
        assert [t["id"] for t in ev["tracers"]] == ["tracer-t2"], ev
        time.sleep(max(0.0, 8.0 - (time.monotonic() - t_cut)))
        lan.link("t1", "up")
        t_up = time.monotonic()
        at_plug = r.last()
        assert r.server_exit() is None and at_plug["committed"] < PHOTONS_REJOIN * 0.5, \
            ("the render was (nearly) over before the cable was back: it tests nothing", at_plug)
        # Back: it learns it was dropped, registers again, gets chunks and
        # sends results, and the render finishes.
        try:
            back = r.wait_for("t1 back, with chunks and results", lambda s: any(
                t["id"] == "tracer-t1" and t["chunks"] and t["results"] for t in s["tracers"]), 20)
            print(f"\nrejoin: back {time.monotonic() - t_up:.1f} s after the cable, {back['tracers']}")
            if "rejoined the server" not in r.log("t1"):
                raise RejoinFailed("the server lists t1 again but t1 never logged that it rejoined "
                                   "(it never got the welcome)\n" + r.procs.tails())
            _wait_while_progressing(r, stall_s=15, limit_s=120)
        except RejoinFailed:
            raise
        except AssertionError as e:
            raise RejoinFailed(str(e)) from None
        res = r.finish()
    finally:
        r.close()
    _assert_exact(res, healthy, photons=PHOTONS_REJOIN)
    k = res["summary"]["counters"]
    assert k["tracers_evicted"] >= 1, k
    final = {t["id"]: t for t in res["summary"]["tracers"]}
    assert sorted(final) == ["tracer-t1", "tracer-t2"] and final["tracer-t1"]["results"] > 0, final


def _wait_while_progressing(r: Render, stall_s: float, limit_s: float) -> None:
    """Wait for the server to exit while it keeps committing photons: a
    render that stops committing for `stall_s` is stuck (the failure this
    looks for); a slow machine only takes longer, up to `limit_s`."""
    deadline = time.monotonic() + limit_s
    last, since = None, time.monotonic()
    while r.server_exit(1.0) is None:
        now, committed = time.monotonic(), r.last().get("committed")
        if committed != last:
            last, since = committed, now
        if now - since > stall_s or now > deadline:
            h = r.history()
            raise RejoinFailed(f"the render {'stalled' if now - since > stall_s else 'ran too long'} after "
                               f"the tracer came back: photons committed {committed:,} for {now - since:.0f} s; "
                               f"last status {h[-1] if h else None}\n{r.procs.tails()}")


def _add_loss_rule(ns: str) -> None:
    if shutil.which("iptables") is None:
        pytest.skip("the `iptables` command is not installed")
    r = subprocess.run(["ip", "netns", "exec", ns, "iptables", "-A", "INPUT", "-i", "eth0", "-m", "statistic",
                        "--mode", "random", "--probability", "0.05", "-j", "DROP"],
                       capture_output=True, text=True, timeout=20)
    if r.returncode != 0:
        pytest.skip(f"cannot add an iptables packet-loss rule: {r.stderr.strip()}")


def _dropped(ns: str) -> int:
    """Packets the loss rule dropped (its counter), -1 if not found."""
    r = subprocess.run(["ip", "netns", "exec", ns, "iptables", "-L", "INPUT", "-v", "-n", "-x"],
                       capture_output=True, text=True, timeout=20)
    for line in r.stdout.splitlines():
        if "DROP" in line and "statistic" in line:
            return int(line.split()[0])
    return -1


def test_five_percent_packet_loss_slows_the_render_down(lan, tmp_path, healthy):
    ns = lan.hosts["t1"][0]
    _add_loss_rule(ns)        # before the start: the whole render is lossy (the rule dies with the namespace)
    # passed=1 only if every assertion holds; a failure records 0.
    with figures.outcome("5% packet loss on a tracer host", "passed", timeout_s=LOSS_TIMEOUT_S) as fig:
        _lossy_render(lan, tmp_path, healthy, ns, fig)


def _lossy_render(lan, tmp_path, healthy, ns: str, fig: dict) -> None:
    res = _render(lan.hosts, tmp_path / "loss", LOSS_TIMEOUT_S)
    dropped = _dropped(ns)
    print(f"packet loss: {dropped} packets dropped at t1; rendered in {res['summary']['seconds']:.1f} s, "
          f"{healthy['summary']['seconds']:.1f} s without loss")
    fig.update(seconds=round(res["summary"]["seconds"], 2), healthy_seconds=round(healthy["summary"]["seconds"], 2),
               packets_dropped=dropped)
    _assert_exact(res, healthy)
    assert dropped > 0, "the rule dropped no packets"
    assert res["summary"]["seconds"] > healthy["summary"]["seconds"], \
        ("5% packet loss did not slow the render", res["summary"]["seconds"], healthy["summary"]["seconds"])
    assert res["summary"]["counters"]["tracers_evicted"] == 0, res["summary"]["counters"]
