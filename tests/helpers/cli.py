"""The one `dosppm` entry point (`python -m services.cli`) run as a child
process, the way a user runs it, and free loopback ports for its sockets."""
from __future__ import annotations

import os
import socket
import subprocess
import sys

from tests.helpers.paths import REPO

DOSPPM = [sys.executable, "-m", "services.cli"]


def child_env(extra: dict | None = None) -> dict:
    """This environment with the checkout first on PYTHONPATH, so a child
    imports this tree's code whatever its working directory."""
    path = [REPO] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(path), **(extra or {})}


def run_python(*args, timeout: float = 300, cwd=REPO, env: dict | None = None) -> subprocess.CompletedProcess:
    """`python ARGS` to completion; stdout and stderr captured as text."""
    return subprocess.run([sys.executable, *map(str, args)], cwd=cwd, env=child_env(env), capture_output=True,
                          text=True, timeout=timeout)


def run_dosppm(*args, timeout: float = 300, cwd=REPO, env: dict | None = None) -> subprocess.CompletedProcess:
    """`dosppm ARGS` to completion; stdout and stderr captured as text."""
    return run_python("-m", "services.cli", *args, timeout=timeout, cwd=cwd, env=env)


def start_dosppm(*args, cwd=REPO, env: dict | None = None, **popen) -> subprocess.Popen:
    """`dosppm ARGS` started in the background (Popen keywords pass through)."""
    return subprocess.Popen([*DOSPPM, *map(str, args)], cwd=cwd, env=child_env(env), **popen)


def free_port() -> int:
    """A TCP port free on 127.0.0.1 just now (the OS's choice)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
