"""The render service across real hosts: a server and two tracers, each in
its own Linux network namespace on a private bridge (the recipe in
RECIPES.md, "Several hosts on one machine"). The tracers get no chunk
store: they fetch their chunks from the server over ZeroMQ into caches of
their own, advertise their namespace address (`--advertise auto`) and
send portal traffic to each other across the bridge.

- server and both workers exit 0; the image equals single-process SPPM's
  (same seed and photons) within noise per 8x8 tile, as docs/correctness.md
  says;
- each worker's cache holds exactly the chunk files of its chunks, each
  matching the SHA-256 of the server's manifest;
- two tracers, each at an endpoint on its own host's address;
- portal rays cross between the tracers; the server's final accounting
  (OUT.json) is exact: photons emitted = completed + abandoned, and
  completed = committed = applied;
- the server's address is not reachable from the root namespace.

Needs root, Linux and `ip` (iproute2); skipped otherwise.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import sys
import time
import urllib.request

import numpy as np
import pytest

from dosppm_core.chunks.store import ChunkStore, is_store
from dosppm_core.film import read_exr
from tests.helpers import netns
from tests.helpers.cli import DOSPPM
from tests.helpers.cluster import assert_same_within_noise, caustic_reference
from tests.helpers.netns import POLLER, Procs

pytestmark = [pytest.mark.netns, pytest.mark.slow]
# The single-process image's settings (tests/helpers/cluster.py), so the
# image is compared with it per tile, as test_cluster_processes.py does.
RENDER = ["--photons", "240000", "--photons-per-iteration", "40000", "--seed", "5", "--min-photon-jobs", "16"]
SERVER_TIMEOUT_S = 90     # start-up (subdivision, numba cache), render, drain, output
WORKER_TIMEOUT_S = 20     # after the server has exited
HTTP_PORT = 8080
ZMQ_PORT = 5555
PEER_PORT = 5600

# A unique name prefix and /24 per test run: parallel or leftover runs on
# this machine cannot clash (the addresses live on a private bridge anyway).
_PID = os.getpid()
PREFIX = f"dosppm-{_PID}"
SUBNET = f"10.213.{_PID % 250 + 1}"
HOSTS = {"server": f"{SUBNET}.1", "t1": f"{SUBNET}.11", "t2": f"{SUBNET}.12"}


@pytest.fixture
def lan():
    """A bridge in namespace <prefix>-lan and one namespace per host with a
    veth into it; yields {host: (namespace, address)}. No default route:
    nothing leaves the machine. The namespaces are always deleted."""
    with netns.lan(PREFIX, HOSTS) as hosts:
        yield hosts


def _chunks_ever_served(log: str) -> set[int]:
    """Every chunk a tracer's log says it was given: at its welcome and in
    each peer table after."""
    ever: set[int] = set()
    for m in re.finditer(r"(?:joined as \d+ at \S+, chunks|this tracer serves chunks) \[([\d, ]*)\]", log):
        ever.update(int(k) for k in m.group(1).replace(",", " ").split())
    return ever


def _reachable_from_root(ip: str, port: int) -> bool:
    try:
        urllib.request.urlopen(f"http://{ip}:{port}/status", timeout=1).close()
        return True
    except OSError:
        return False


def test_server_and_two_tracers_on_separate_hosts(lan, tmp_path):
    server_ns, server_ip = lan["server"]
    store_cache, out = tmp_path / "store-cache", tmp_path / "out.exr"
    status_file = tmp_path / "status.json"
    logs = tmp_path / "logs"
    logs.mkdir()
    py = DOSPPM
    env = {"DOSPPM_LOG_LEVEL": "info", "PYTHONUNBUFFERED": "1"}
    netns.warm_kernel_cache(tmp_path / "warm-up")
    procs = Procs(logs)
    try:
        procs.start("server", server_ns, py + [
            "server", "cornell-caustic", "--bind", f"tcp://{server_ip}:{ZMQ_PORT}",
            "--http", f"{server_ip}:{HTTP_PORT}", "--min-tracers", "2", *RENDER,
            "--out", str(out), "--width", "64", "--height", "64", "--chunks", "4",
            "--store-cache", str(store_cache), "--quiet"], env)
        for h in ("t1", "t2"):
            ns, _ = lan[h]
            procs.start(h, ns, py + [
                "worker", "--server", f"tcp://{server_ip}:{ZMQ_PORT}", "--bind", f"tcp://0.0.0.0:{PEER_PORT}",
                "--advertise", "auto", "--cache-dir", str(tmp_path / f"cache-{h}"), "--threads", "1",
                "--id", f"tracer-{h}", "--retry", "60", "--quiet"], env)
        procs.start("poller", lan["t1"][0], [sys.executable, "-c", POLLER,
                                             f"http://{server_ip}:{HTTP_PORT}/status", str(status_file),
                                             str(SERVER_TIMEOUT_S + 10)])

        # While the server runs: once its status page answers across the
        # bridge, it must not answer from the root namespace.
        deadline = time.monotonic() + SERVER_TIMEOUT_S
        root_checked = False
        server_rc = None
        while time.monotonic() < deadline:
            server_rc = procs.wait("server", 0.5)
            if server_rc is not None:
                break
            if not root_checked and status_file.exists():
                assert not _reachable_from_root(server_ip, HTTP_PORT), \
                    f"the server's status page at {server_ip} answers from the root namespace"
                root_checked = True
        assert server_rc == 0, (f"server still running after {SERVER_TIMEOUT_S} s" if server_rc is None
                                else f"server exit status {server_rc}") + "\n" + procs.tails()
        worker_deadline = time.monotonic() + WORKER_TIMEOUT_S
        for h in ("t1", "t2"):
            rc = procs.wait(h, worker_deadline - time.monotonic())
            assert rc == 0, (f"worker {h} still running {WORKER_TIMEOUT_S} s after the server's exit" if rc is None
                             else f"worker {h} exit status {rc}") + "\n" + procs.tails()
        poller = procs.procs["poller"]
        if poller.poll() is None:
            os.killpg(poller.pid, signal.SIGKILL)
            poller.wait(timeout=10)
    finally:
        procs.kill_all()
    tails = procs.tails()
    assert root_checked, "never saw the status page while the server ran\n" + tails

    # The image.
    assert out.exists() and out.with_suffix(".png").exists(), tails
    img, _ = read_exr(str(out))
    assert img.shape[:2] == (64, 64), img.shape
    assert np.isfinite(img).all(), "non-finite pixels"
    ref = caustic_reference()
    assert_same_within_noise(img, ref[5][0], ref[9][0])

    # The last status seen.
    st = json.loads(status_file.read_text())
    tracers = {t["id"]: t for t in st["tracers"]}
    assert sorted(tracers) == ["tracer-t1", "tracer-t2"], (st["tracers"], tails)
    endpoints = {h: tracers[f"tracer-{h}"]["endpoint"] for h in ("t1", "t2")}
    assert endpoints == {h: f"tcp://{lan[h][1]}:{PEER_PORT}" for h in ("t1", "t2")}, (endpoints, tails)
    # Portal traffic: in the last poll, or in the summary's table (a short
    # render may end between two polls).
    summary = json.loads(out.with_suffix(".json").read_text()) if out.with_suffix(".json").exists() else {}
    portal_out = max(sum(t.get("portal_rays_out", 0) for t in tt) for tt in (st["tracers"], summary.get("tracers", [])))
    assert portal_out > 0, (f"no portal traffic between the tracers: {st['tracers']}", tails)
    c = st["counters"]
    assert c["over_credited_jobs"] == 0 and c["stale_paths"] == 0, (c, tails)
    # The last poll may come before the first commit of a short render:
    # that photons were committed is the summary's to say (below).
    assert c["photons_committed"] <= c["photons_emitted"], c
    # The server's own accounting of the whole run (OUT.json beside the
    # image, written after the drain): exact, unlike a status polled while
    # photons were still in flight.
    summary_file = out.with_suffix(".json")
    assert summary_file.exists(), "the server wrote no OUT.json accounting beside the image\n" + tails
    summary = json.loads(summary_file.read_text())
    sc = summary["counters"]
    assert sc["photons_emitted"] >= 240_000 and sc["photons_committed"] > 0, (sc, tails)
    # Jobs still in flight at the end are abandoned whole and counted
    # (none with --photons); every other photon is committed and applied.
    assert sc["photons_emitted"] == sc["photons_completed"] + sc["photons_abandoned"], sc
    assert sc["photons_completed"] == sc["photons_committed"] \
        == summary.get("photons_applied", sc["photons_committed"]), (sc, summary.get("photons_applied"))
    assert summary["jobs_in_flight"] == 0, summary["jobs_in_flight"]
    assert sc["over_credited_jobs"] == 0 and sc["stale_paths"] == 0, sc
    served = {h: sorted(tracers[f"tracer-{h}"]["chunks"]) for h in ("t1", "t2")}
    assert sorted(served["t1"] + served["t2"]) == [0, 1, 2, 3], (served, tails)   # c > n: disjoint

    # The chunks: each worker fetched exactly its own, byte for byte those
    # of the server's store.
    stores = [p for p in store_cache.iterdir() if is_store(str(p))]
    assert len(stores) == 1, stores
    store = ChunkStore.open(str(stores[0]))
    for h in ("t1", "t2"):
        # The join line names the chunks of the welcome; every later table
        # (a join, or the balancer moving chunks by measured rays) is logged
        # as "peer table N: this tracer serves chunks [...]". A tracer's
        # cache holds the chunks it serves at the end and may keep ones it
        # served earlier, never one it was not given.
        log = procs.err(h, chars=10**6)
        assert f"tracer tracer-{h} joined as" in log and f"at {endpoints[h]}, chunks " in log, (h, log[-2000:])
        ever = _chunks_ever_served(log)
        cache = tmp_path / f"cache-{h}" / store.key
        assert cache.is_dir(), (h, list((tmp_path / f"cache-{h}").iterdir()))
        files = {p.name for p in cache.iterdir() if p.name.startswith("chunk-")}
        file_of = {k: store.manifest["chunks"][k]["file"] for k in range(len(store.manifest["chunks"]))}
        assert {file_of[k] for k in served[h]} <= files <= {file_of[k] for k in ever}, \
            (h, served[h], sorted(ever), sorted(files), c.get("rebalanced"))
        for k in (k for k in file_of if file_of[k] in files):
            entry = store.manifest["chunks"][k]
            data = (cache / entry["file"]).read_bytes()
            assert len(data) == entry["file_bytes"], (h, k)
            assert hashlib.sha256(data).hexdigest() == entry["sha256"], (h, k)
