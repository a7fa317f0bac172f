"""Load: sixteen tracers on this 2-core machine, 1k photon jobs in flight,
c = 16. The server's resident memory stays under a stated limit, no
message is dropped (every photon accounted for exactly once), and a tracer
stopped for a while back-pressures the others through the server's queue
allowance instead of letting their outboxes grow without bound."""
from __future__ import annotations

import json
import signal
import time
import urllib.request

import pytest

from tests.helpers import figures
from tests.helpers.cli import free_port, start_dosppm

pytestmark = pytest.mark.slow   # a server and sixteen tracer processes
TRACERS = 16
# The stated bound on the server's peak RSS with 16 tracers and 1k jobs in
# flight: about 150 MiB idle (Python, numba, the kernels) plus a few copies
# of one 1M-deposit photon batch (44 MB each: held, concatenated, split,
# queued for the statistics thread, sorted), plus photon jobs under the
# tracers' shared queue allowance (TOTAL_ALLOWANCE_RAYS, 64 MB). Measured
# 654-736 MiB when a deposit was 56 B (it carried a normal).
SERVER_RSS_LIMIT = 900 << 20
# Rays one tracer may hold for its peers: its queue allowance (262,144
# rays) plus what was in flight to it when that ran out, with margin.
OUTBOX_RAYS_LIMIT = 2_000_000


def _rss(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def test_sixteen_tracers_keep_the_server_bounded(tmp_path):
    # passed=1 only if every assertion holds; a failure records 0.
    with figures.outcome("16 tracers, 1k jobs in flight, one stopped 8 s", "passed", timeout_s=60) as fig:
        _sixteen_tracers(tmp_path, fig)


def _sixteen_tracers(tmp_path, fig: dict) -> None:
    port, http = free_port(), free_port()
    server = start_dosppm(
        "server", "cornell-box", "--width", "64", "--height", "64", "--chunks", "16",
        "--bind", f"tcp://127.0.0.1:{port}", "--http", f"127.0.0.1:{http}", "--min-tracers", str(TRACERS),
        # 1,024-photon jobs (not the service's 4,096): 1k jobs in flight
        # is then 1M photons, a third of the render, as the bound was set.
        "--photons", "3e6", "--photons-per-job", "1024", "--tracer-timeout", "60", "--threads", "1",
        "--out", str(tmp_path / "img.exr"),
        "--store-cache", str(tmp_path / "stores"), "--quiet", stderr=open(tmp_path / "server.log", "w"))
    workers = [start_dosppm("worker", "--server", f"tcp://127.0.0.1:{port}", "--threads", "1",
                            "--id", f"w{i}", "--cache-dir", str(tmp_path / f"c{i}"), "--quiet",
                            stderr=open(tmp_path / f"w{i}.log", "w")) for i in range(TRACERS)]
    peak, statuses, stopped = 0, [], False
    try:
        deadline = time.monotonic() + 400
        while server.poll() is None and time.monotonic() < deadline:
            peak = max(peak, _rss(server.pid))
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{http}/status", timeout=2) as r:
                    st = json.load(r)
                statuses.append(st)
            except OSError:
                st = {}
            # Once rendering, stop one tracer for 8 s: the rest must not
            # buffer without bound for it.
            if not stopped and st.get("photons_committed", 0) > 0:
                workers[3].send_signal(signal.SIGSTOP)
                stopped = time.monotonic()
            if stopped and stopped is not True and time.monotonic() - stopped > 8:
                workers[3].send_signal(signal.SIGCONT)
                stopped = True
            time.sleep(0.2)
        assert server.wait(60) == 0, (tmp_path / "server.log").read_text()[-2000:]
    finally:
        for p in (server, *workers):
            if p.poll() is None:
                p.send_signal(signal.SIGCONT)
                p.kill()
                p.wait()
    outbox = max((t.get("outbox_rays", 0) for s in statuses for t in s.get("tracers", [])), default=0)
    fig.update(server_peak_rss_mib=peak >> 20, rss_limit_mib=SERVER_RSS_LIMIT >> 20, largest_outbox_rays=outbox,
               outbox_limit_rays=OUTBOX_RAYS_LIMIT)
    with open(tmp_path / "img.json", encoding="utf-8") as f:
        summary = json.load(f)
    k = summary["counters"]
    assert len(summary["tracers"]) == TRACERS
    assert max(s.get("photon_jobs_in_flight", 0) for s in statuses) >= 1000
    # Nothing dropped: every photon sent was completed and applied once.
    assert k["photons_emitted"] - k["photons_discarded"] == k["photons_completed"] == k["photons_committed"]
    # A message that found no connection (the stopped tracer reconnects
    # when it wakes: 8 s is past its 5 s of server silence) drops that
    # tracer, and its jobs are re-emitted: the counts above stay exact.
    assert k["over_credited_jobs"] == 0
    assert summary.get("undeliverable", 0) == 0 or k["tracers_evicted"] >= 1, k
    assert peak < SERVER_RSS_LIMIT, f"server peak RSS {peak >> 20} MiB"
    assert outbox < OUTBOX_RAYS_LIMIT, f"a tracer held {outbox} rays for its peers"
    print(f"server peak RSS {peak >> 20} MiB; largest outbox {outbox} rays; "
          f"photons {k['photons_committed']:,}")
