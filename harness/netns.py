"""Hosts as Linux network namespaces on a private bridge (RECIPES.md,
"Several hosts on one machine"), for the multi-host tests and the
slow-link benchmark: the bridge, one namespace per host with a veth
`eth0` into it, and a rate limit on a host's link (`tc ... tbf`, both
directions). No default route anywhere: nothing leaves the machine.
Every namespace made is deleted again, whatever happens."""
from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys


class NetnsUnavailable(RuntimeError):
    """This machine cannot make network namespaces (the reason is the message)."""


def ip(*args, check=True):
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20, check=check)


def netns_unavailable(prefix: str) -> str | None:
    """Why this machine cannot run the multi-host tests, or None."""
    if not sys.platform.startswith("linux"):
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return "creating network namespaces needs root"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    probe = f"{prefix}-probe"
    try:
        r = ip("netns", "add", probe, check=False)
    except (OSError, subprocess.SubprocessError) as e:
        return f"cannot create a network namespace (`ip netns add` failed: {e})"
    if r.returncode != 0:
        return f"cannot create a network namespace: {r.stderr.strip()}"
    ip("netns", "del", probe, check=False)
    return None


def delete_namespaces(names) -> None:
    for ns in names:
        ip("netns", "del", ns, check=False)


@contextlib.contextmanager
def lan(prefix: str, hosts: dict[str, str]):
    """A bridge in namespace <prefix>-lan and one namespace <prefix>-<host>
    per host with a veth `eth0` into it (the bridge's end is `v-<host>`,
    in the bridge namespace); yields {host: (namespace, address)}. Raises
    NetnsUnavailable where namespaces cannot be made, and
    subprocess.CalledProcessError when building the bridge fails."""
    why = netns_unavailable(prefix)
    if why:
        raise NetnsUnavailable(why)
    bridge_ns = f"{prefix}-lan"
    made = []
    try:
        ip("netns", "add", bridge_ns)
        made.append(bridge_ns)
        ip("-n", bridge_ns, "link", "set", "lo", "up")
        ip("-n", bridge_ns, "link", "add", "br0", "type", "bridge")
        ip("-n", bridge_ns, "link", "set", "br0", "up")
        out = {}
        for h, addr in hosts.items():
            ns = f"{prefix}-{h}"
            ip("netns", "add", ns)
            made.append(ns)
            ip("-n", ns, "link", "set", "lo", "up")
            ip("link", "add", f"v-{h}", "netns", bridge_ns, "type", "veth", "peer", "name", "eth0", "netns", ns)
            ip("-n", bridge_ns, "link", "set", f"v-{h}", "master", "br0", "up")
            ip("-n", ns, "addr", "add", f"{addr}/24", "dev", "eth0")
            ip("-n", ns, "link", "set", "eth0", "up")
            out[h] = (ns, addr)
    except BaseException:
        delete_namespaces(reversed(made))
        raise
    try:
        yield out
    finally:
        delete_namespaces(reversed(made))


def limit_rate(prefix: str, host: str, rate_bit_s: float) -> None:
    """Cap `host`'s link at `rate_bit_s` each way, as a NIC of that speed
    would: a token bucket on its `eth0` (what it sends) and on the bridge's
    end of its veth (what it receives). The burst is 1 ms at the rate (at
    least 64 KiB), the queue 50 ms."""
    if shutil.which("tc") is None:
        raise NetnsUnavailable("the `tc` command (iproute2) is not installed")
    burst = max(64 << 10, int(rate_bit_s / 8 / 1000))
    for ns, dev in ((f"{prefix}-{host}", "eth0"), (f"{prefix}-lan", f"v-{host}")):
        subprocess.run(["tc", "-n", ns, "qdisc", "replace", "dev", dev, "root", "tbf", "rate",
                        f"{int(rate_bit_s)}bit", "burst", str(burst), "latency", "50ms"],
                       capture_output=True, text=True, timeout=20, check=True)


def link_bytes(prefix: str, host: str) -> tuple[int, int]:
    """(bytes received, bytes sent) by `host`'s eth0 so far."""
    def read(what: str) -> int:
        r = ip("netns", "exec", f"{prefix}-{host}", "cat", f"/sys/class/net/eth0/statistics/{what}_bytes")
        return int(r.stdout.strip())
    return read("rx"), read("tx")
