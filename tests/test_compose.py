"""The Docker image and docker-compose.yml end to end, as a test of the
`docker` tier: it runs `.ci/compose-check`, which starts a private dockerd,
builds the image from a debootstrapped base, renders the built-in Cornell
box with a server and two tracers under compose and checks /status, the
healthchecks, the exit codes and the EXR (the script's header lists them).

It needs root and Docker's packages (docker.io, docker-compose,
debootstrap), which `.ci/run` installs before the tests; it skips where they
are missing, and under DOSPPM_REQUIRE_ALL=1 that skip fails (its reason
names docker). A runner that has no Docker deselects the tier (`-m "not
docker"`): then nothing skips, and nothing claims the check ran.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

import pytest

from tests.helpers.paths import REPO

TIMEOUT_S = 1800     # debootstrap about 50 s, the image's pip install, a 15 s render
pytestmark = [pytest.mark.docker, pytest.mark.slow, pytest.mark.timeout(TIMEOUT_S + 60)]
CHECK = os.path.join(REPO, ".ci", "compose-check")
CHECKS = 5       # image built, /status, healthchecks, exit codes, EXR


def missing_docker() -> str | None:
    """Why the compose check cannot run here, or None. It installs nothing
    itself when run from the tests: a developer's `pytest` must not
    apt-get Docker onto their machine."""
    if not sys.platform.startswith("linux"):
        return "the docker compose check needs Linux"
    if os.geteuid() != 0:
        return "the docker compose check needs root (it starts its own dockerd)"
    absent = [t for t in ("dockerd", "debootstrap") if shutil.which(t) is None]
    if shutil.which("docker-compose") is None and shutil.which("docker") is None:
        absent.append("docker-compose")
    if absent:
        return f"docker is not installed ({', '.join(absent)} missing; .ci/run installs docker.io, " \
               "docker-compose and debootstrap)"
    return None


def test_the_image_and_compose_file_render_a_cluster():
    why = missing_docker()
    if why:
        pytest.skip(why)
    try:
        r = subprocess.run([CHECK], cwd=REPO, capture_output=True, text=True, timeout=TIMEOUT_S,
                           stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"compose-check ran over {TIMEOUT_S} s: {(e.stdout or '')[-3000:]}")
    print(r.stdout)
    tail = r.stdout[-3000:] + "\n--- stderr:\n" + r.stderr[-3000:]
    assert r.returncode == 0, tail
    # Its own tally, so a check dropped from the script shows here.
    assert re.search(rf"^compose-check: {CHECKS} passed, 0 failed$", r.stdout, re.M), tail
