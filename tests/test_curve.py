"""CURVE on the LAN: with keys made by `dosppm keys`, the server admits
only tracers whose public keys it lists; tracers talk to each other
encrypted too; a tracer with an unlisted key, or without CURVE, gets no
answer and gives up with a one-line error. A tracer's own peer socket,
probed mid-render, completes a handshake only with a listed key: in plain
text, or with an unlisted key, it accepts nothing."""
from __future__ import annotations

import json
import os
import shutil
import subprocess

import pytest

from services import transport
from tests.helpers.cli import free_port, run_dosppm, start_dosppm

pytestmark = pytest.mark.slow   # a server and four tracer processes


def test_only_listed_tracers_join_a_curve_server(tmp_path):
    keys, allowed = tmp_path / "keys", tmp_path / "allowed"
    made = run_dosppm("keys", "server", "t1", "t2", "intruder", "--out", keys, timeout=60)
    assert made.returncode == 0, made.stderr
    assert oct(os.stat(keys / "t1.key_secret").st_mode & 0o777) == "0o600"
    allowed.mkdir()
    for name in ("t1", "t2"):
        shutil.copy(keys / f"{name}.key", allowed / f"{name}.key")
    port = free_port()
    server = start_dosppm(
        "server", "cornell-box", "--width", "32", "--height", "32", "--chunks", "2",
        "--bind", f"tcp://127.0.0.1:{port}", "--http", "off", "--min-tracers", "2", "--photons", "4e6",
        "--out", str(tmp_path / "img.exr"), "--store-cache", str(tmp_path / "stores"), "--quiet",
        "--curve-secret", str(keys / "server.key_secret"), "--curve-clients", str(allowed),
        stderr=subprocess.PIPE, text=True)

    def worker(name, *curve, retry="60"):
        return start_dosppm(
            "worker", "--server", f"tcp://127.0.0.1:{port}", "--threads", "1", "--id", name,
            "--cache-dir", str(tmp_path / name), "--retry", retry, *curve, stderr=subprocess.PIPE, text=True)

    def curve(name):
        return ("--curve-secret", str(keys / f"{name}.key_secret"), "--curve-server-key",
                str(keys / "server.key"), "--curve-clients", str(allowed))
    # Refused first, so the render cannot start with them: an unlisted key,
    # and a tracer without CURVE.
    intruder = worker("intruder", *curve("intruder"), retry="8")
    plain = worker("plain", retry="8")
    assert intruder.wait(60) == 1 and "no answer from server" in intruder.stderr.read()
    assert plain.wait(60) == 1
    good = [worker(n, *curve(n)) for n in ("t1", "t2")]
    try:
        peer = _peer_endpoint(good[0])
        t1_public, _ = transport.load_keys(str(keys / "t1.key"))
        probes = {who: transport.handshake(peer, *key) for who, key in (
            ("plain", ()), ("intruder", (str(keys / "intruder.key_secret"), t1_public)),
            ("t2", (str(keys / "t2.key_secret"), t1_public)))}
        assert probes["t2"] == "accepted", probes            # the probe works: a listed peer gets in
        assert probes["plain"] != "accepted" and probes["intruder"] != "accepted", probes
        assert server.wait(180) == 0, server.stderr.read()[-2000:]
        for w in good:
            assert w.wait(30) == 0, w.stderr.read()[-2000:]
    finally:
        for p in (server, *good):
            if p.poll() is None:
                p.kill()
    with open(tmp_path / "img.json", encoding="utf-8") as f:
        summary = json.load(f)
    assert {t["id"] for t in summary["tracers"]} == {"t1", "t2"}
    assert sum(t.get("portal_rays_out", 0) for t in summary["tracers"]) > 0   # peers talked, encrypted
    k = summary["counters"]
    assert k["photons_committed"] > 0 and k["photons_emitted"] == k["photons_committed"]


def _peer_endpoint(worker) -> str:
    """The peer socket a tracer announces as it registers ("portals at ...")."""
    for line in worker.stderr:
        if "portals at " in line:
            return line.split("portals at ", 1)[1].split()[0].rstrip(",")
    raise AssertionError("the tracer never said where its peer socket is")
