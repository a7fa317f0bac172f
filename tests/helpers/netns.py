"""Shared by the multi-host tests (tests/test_netns.py,
tests/test_netns_faults.py): hosts as Linux network namespaces on a
private bridge (RECIPES.md, "Several hosts on one machine"), processes
started in them, and a status poller that runs inside a host.

No default route anywhere: nothing leaves the machine. Every namespace
made is deleted again, whatever happens (processes and iptables rules in
a namespace die with it)."""
from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys

import pytest

from tests.helpers.cli import run_dosppm
from tests.helpers.paths import REPO


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
    in the bridge namespace); yields {host: (namespace, address)}. Skips
    the test where namespaces cannot be made."""
    why = netns_unavailable(prefix)
    if why:
        pytest.skip(why)
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
    except subprocess.CalledProcessError as e:
        delete_namespaces(reversed(made))
        pytest.fail(f"building the bridge failed: {' '.join(e.cmd)}: {e.stderr.strip()}")
    except BaseException:
        delete_namespaces(reversed(made))
        raise
    try:
        yield out
    finally:
        delete_namespaces(reversed(made))


class Procs:
    """Processes started in namespaces, their output in files; all killed
    (by process group) at the end."""

    def __init__(self, folder):
        self.folder, self.procs = folder, {}

    def start(self, name, ns, argv, env=None):
        out = open(self.folder / f"{name}.out", "wb")
        err = open(self.folder / f"{name}.err", "wb")
        try:
            p = subprocess.Popen(["ip", "netns", "exec", ns, *argv], cwd=REPO, stdout=out, stderr=err,
                                 stdin=subprocess.DEVNULL, env={**os.environ, **(env or {})},
                                 start_new_session=True)
        finally:
            out.close()
            err.close()
        self.procs[name] = p
        return p

    def wait(self, name, timeout):
        """The exit status, or None on a time-out."""
        try:
            return self.procs[name].wait(timeout=max(timeout, 0.1))
        except subprocess.TimeoutExpired:
            return None

    def err(self, name, chars=3000) -> str:
        try:
            text = (self.folder / f"{name}.err").read_text(errors="replace")
        except OSError:
            return ""
        return text[-chars:]

    def tails(self) -> str:
        return "\n".join(f"--- {n} (exit {p.poll()}) stderr tail:\n{self.err(n)}" for n, p in self.procs.items())

    def kill(self, name):
        p = self.procs[name]
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pass

    def kill_all(self):
        for p in self.procs.values():
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        for p in self.procs.values():
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pass


# Runs inside a host: polls the server's status page and keeps the last
# good JSON in a file (written atomically) until killed or the deadline
# passes.
POLLER = r"""
import json, os, sys, time, urllib.request
url, out, deadline = sys.argv[1], sys.argv[2], time.time() + float(sys.argv[3])
n = 0
while time.time() < deadline:
    try:
        with urllib.request.urlopen(url, timeout=2) as r:
            doc = json.loads(r.read())
        n += 1
        doc["_poll"] = {"n": n, "t": time.time()}
        with open(out + ".tmp", "w") as f:
            json.dump(doc, f)
        os.replace(out + ".tmp", out)
    except Exception:
        pass
    time.sleep(0.3)
"""


def warm_kernel_cache(folder) -> None:
    """Compile (or load) the numba kernels once, in a small local render of
    the same layout: every process of the test shares numba's on-disk
    cache, and the whole package's cache is dropped whenever a kernel
    module changes. A cold cache costs each process 10-20 s of compiling,
    which would eat the render and leave no photons, no portal traffic.
    `--iterations` (not `--time`) so the photon kernels surely run."""
    folder.mkdir()
    try:
        r = run_dosppm("render", "cornell-box", "--tracers", "2", "--chunks", "4", "--width", "16", "--height",
                       "16", "--iterations", "2", "--min-photon-jobs", "64", "--http", "off", "--store-cache",
                       folder / "store-cache", "--out", folder / "warm.exr", "--quiet", timeout=180)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"warming the kernel cache took over {e.timeout} s: {(e.stderr or '')[-3000:]}")
    assert r.returncode == 0, f"warm-up render failed ({r.returncode}): {r.stderr[-3000:]}"
