"""Shared by the multi-host tests (tests/test_netns*.py): hosts as Linux
network namespaces on a private bridge (harness/netns.py, the
recipe in RECIPES.md), processes started in them, and a status poller
that runs inside a host. Processes and iptables rules in a namespace die
with it."""
from __future__ import annotations

import contextlib
import os
import signal
import subprocess

import pytest

from harness.netns import NetnsUnavailable, delete_namespaces, ip, netns_unavailable  # noqa: F401
from harness.netns import lan as _lan
from tests.helpers.cli import run_dosppm
from tests.helpers.paths import REPO


@contextlib.contextmanager
def lan(prefix: str, hosts: dict[str, str]):
    """harness/netns.lan for a test: skipped where namespaces
    cannot be made, failed (with the command) where building the bridge
    fails. Yields {host: (namespace, address)}."""
    try:
        ctx = _lan(prefix, hosts)
        out = ctx.__enter__()
    except NetnsUnavailable as e:
        pytest.skip(str(e))
    except subprocess.CalledProcessError as e:
        pytest.fail(f"building the bridge failed: {' '.join(e.cmd)}: {e.stderr.strip()}")
    try:
        yield out
    finally:
        ctx.__exit__(None, None, None)


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
