"""A cluster on a slow link (issue 32 step 6): the replay harness's server
on its own host whose link is capped (`tc tbf`, both directions), fed by
two synthetic tracers on two other hosts (harness/replay.py).

- the render ends normally and its accounting is exact (photons emitted
  = completed + abandoned + discarded; completed = committed);
- the cap holds: the server's link carried no more than its rate, and the
  photons applied per second stay under the link's ceiling (the rate over
  the bytes per photon of the busier direction, as the server counts
  them), which is what benchmarks/slow_link.py's "limited by" rests on.

The figures at 1 Gbit/s are benchmarks/slow_link.py's, not asserted here.
(Measured before tracers made their own eye rays: at 40 Mbit/s the
gather at the tracers committed nothing in 12 s, every eye iteration
sending each tracer its eye rays, 56 B a pixel, and its hit points, 40 B a
pixel. The hit points still cross the link.)
Needs root, Linux, `ip` and `tc` (iproute2); skipped otherwise.
"""
from __future__ import annotations

import os
import time

import pytest

from harness import replay
from harness.netns import NetnsUnavailable, limit_rate, link_bytes
from tests.helpers import netns

pytestmark = [pytest.mark.netns, pytest.mark.slow]
_PID = os.getpid()
PREFIX = f"dosppm-lk-{_PID}"
SUBNET = f"10.217.{_PID % 250 + 1}"
HOSTS = {"server": f"{SUBNET}.1", "t1": f"{SUBNET}.11", "t2": f"{SUBNET}.12"}
SECONDS = 12.0


@pytest.fixture
def lan():
    with netns.lan(PREFIX, HOSTS) as hosts:
        yield hosts


# Gigabit, as the issue asks, both ways of gathering; and 40 Mbit/s, where
# the link, not the CPU, surely limits, so the ceiling check bites.
@pytest.mark.parametrize("rate_bit_s, gather_at", [(1e9, "tracers"), (1e9, "server"), (40e6, "server")])
def test_a_server_behind_a_slow_link(lan, tmp_path, rate_bit_s, gather_at):
    try:
        limit_rate(PREFIX, "server", rate_bit_s)
    except NetnsUnavailable as e:
        pytest.skip(str(e))
    rx0, tx0 = link_bytes(PREFIX, "server")
    t0 = time.monotonic()
    s = replay.run("cornell-glass", 2, SECONDS, str(tmp_path), ("--gather-at", gather_at),
                   hosts={"server": lan["server"], "tracers": [lan["t1"][0], lan["t2"][0]]})
    wall = time.monotonic() - t0
    rx1, tx1 = link_bytes(PREFIX, "server")
    c = s["counters"]
    assert c["photons_committed"] > 0, c
    assert c["photons_emitted"] == c["photons_completed"] + c["photons_abandoned"] + c["photons_discarded"], c
    assert c["photons_completed"] == c["photons_committed"], c
    # The cap held, each way (the whole run's traffic, start-up included).
    assert 8 * (rx1 - rx0) / wall <= 1.1 * rate_bit_s
    assert 8 * (tx1 - tx0) / wall <= 1.1 * rate_bit_s
    f = replay.figures(s, per_core=1.0)
    ceiling = rate_bit_s / 8 / max(f["bytes_in_per_photon"], f["bytes_out_per_photon"])
    print(f"gather at {gather_at}: {f['photons_per_s']:,.0f} photons/s applied, link ceiling {ceiling:,.0f}, "
          f"{f['bytes_in_per_photon']:.1f} B in and {f['bytes_out_per_photon']:.1f} B out per photon")
    assert f["photons_per_s"] <= 1.2 * ceiling
