"""Fuzzing the wire and the roles' handlers: 100k random and mutated
frames go to the decoder, and everything that decodes goes to the server's
and a tracer's handlers. Nothing may raise but WireError (decoder) or come
back as anything but replies (handlers); no frame may take long (no hang);
memory stays bounded; and no fabricated deposit reaches the statistics."""
from __future__ import annotations

import heapq
import re
import time
import tracemalloc

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dosppm_core.settings import RenderSettings
from services import wire
from services.server.options import ServerOptions
from services.server.state import ServerState
from services.tracer.state import TracerState
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree
from tests.helpers.scenes import small_scene
from tests.test_wire import sample_fields

FRAMES = 100_000


@pytest.fixture(scope="module")
def roles():
    scene = small_scene("cornell-box", 16)
    provider = MemoryChunks(scene, uniform_tree(root_box(scene), (2, 1, 1)))
    server = ServerState(provider.header, provider.tree, RenderSettings(photons_per_job=64, tile_pixels=64),
                         "k", options=ServerOptions(min_photon_jobs=8))
    reg = wire.decode(wire.encode("register", tracer_id="t", capacity={"cores": 1, "memory_bytes": 0},
                                  endpoint="inproc://t", has_store=True, store_key="k"))
    server.on_register("t", reg, 0.0)
    tracer = TracerState("inproc://t", provider, 4, seed=0)
    tracer.set_peers(1, [["inproc://t"], ["inproc://t"]])
    yield server, tracer
    tracer.close()


def _mutate(frames: list[bytes], rng: np.random.Generator) -> list[bytes]:
    """One of: flip bytes, truncate, extend, drop/duplicate/swap frames,
    rewrite a header field with a random value, or pure noise."""
    frames = [bytearray(f) for f in frames]
    kind = rng.integers(8)
    i = int(rng.integers(len(frames)))
    f = frames[i]
    if kind == 0 and len(f):
        for _ in range(int(rng.integers(1, 8))):
            f[int(rng.integers(len(f)))] = int(rng.integers(256))
    elif kind == 1:
        frames[i] = f[:int(rng.integers(len(f) + 1))]
    elif kind == 2:
        frames[i] = f + bytes(rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8))
    elif kind == 3 and len(frames) > 1:
        frames.pop(i)
    elif kind == 4:
        frames.insert(i, bytearray(f))
    elif kind == 5:
        frames = [frames[0]] + frames[1:][::-1]
    elif kind == 6:
        header = msgpack.unpackb(bytes(frames[0]))
        key = list(header)[int(rng.integers(len(header)))]
        header[key] = [None, -1, 2**64 - 1, "x" * 300, 1.5, [1, [2]], {"a": b"b"}, True][int(rng.integers(8))]
        frames[0] = bytearray(msgpack.packb(header))
    else:
        frames = [bytearray(rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8))
                  for _ in range(int(rng.integers(1, 4)))]
    return [bytes(x) for x in frames]


def _feed(server, tracer, msg) -> None:
    """A decoded message to whichever role takes it; only replies come back."""
    now = 1.0
    if msg.type == "register":
        outs = server.on_register("fuzz", msg, now)
    elif msg.type in ("heartbeat", "results", "chunk_request", "error"):
        outs = server.on_message("t", msg, now)
    elif msg.type in ("photon_job", "eye_job") and msg.counts.sum() > 100_000:
        outs = []      # valid, but making that many paths would only slow the fuzzing down
    elif msg.type in ("photon_job", "eye_job", "portal_rays"):
        try:
            outs = tracer.handle(msg)
        except ValueError as e:
            # The only refusal the state makes itself: a chunk the wire
            # cannot know is out of range (the shell answers it with an
            # error message). Anything else is a bug.
            assert type(e) is ValueError and re.fullmatch(r"chunk -?\d+ out of range \(scene has \d+\)",
                                                          str(e)), repr(e)
            outs = []
    else:
        outs = []
    assert isinstance(outs, list)


def _decode_cpu_s(frames: list[bytes], repeats: int = 3) -> float:
    """The least CPU time of a few decodes of one frame."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.thread_time()
        try:
            wire.decode(frames)
        except wire.WireError:
            pass
        best = min(best, time.thread_time() - t0)
    return best


@pytest.mark.slow   # about 30 s
def test_100k_mutated_frames(roles):
    server, tracer = roles
    rng = np.random.default_rng(2026)
    types = sorted(wire.MESSAGES)
    valid = [[bytes(f) for f in wire.encode(t, **sample_fields(t, int(rng.integers(0, 6)), rng, v))]
             for t in types for v in range(4)]
    decoded = errors = 0
    slowest: list[tuple[float, int, list[bytes]]] = []     # a heap of the slowest frames
    tracemalloc.start()
    base = None
    for k in range(FRAMES):
        frames = _mutate(valid[k % len(valid)], rng) if k % 10 else valid[k % len(valid)]
        t0 = time.thread_time()   # this thread's CPU: neither a shared machine's stalls nor other threads
        try:
            msg = wire.decode(frames)
        except wire.WireError as e:
            errors += 1
            assert "\n" not in str(e) and len(str(e)) < 400
            continue
        finally:
            heapq.heappush(slowest, (time.thread_time() - t0, k, frames))
            if len(slowest) > 5:
                heapq.heappop(slowest)
        decoded += 1
        _feed(server, tracer, msg)
        if tracer.queued_rays > 100_000:      # the tracer would trace these; here, forget them
            tracer.reset()
        if k == FRAMES // 10:
            base = tracemalloc.get_traced_memory()[0]
    current = tracemalloc.get_traced_memory()[0]
    tracemalloc.stop()
    assert decoded > 10_000 and errors > 50_000, (decoded, errors)
    # A frame that was slow once (a garbage collection may fall inside
    # any decode) must be slow every time to be the decoder's fault.
    worst = max(_decode_cpu_s(frames) for _, _, frames in slowest)
    assert worst < 0.5, f"one frame takes {worst:.3f} s of CPU to decode"
    assert current - base < 64 << 20, f"memory grew by {(current - base) >> 20} MiB"
    # Results for jobs that never existed were counted stale, and none of
    # their fabricated deposits is held for the statistics.
    assert server.counters["deposits_received"] == 0
    assert len(server.tracers) <= 1 + 1       # "t" and the fuzzing identity


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.lists(st.binary(max_size=300), min_size=1, max_size=5))
def test_arbitrary_frames_never_crash_the_decoder(data):
    try:
        wire.decode(data)
    except wire.WireError:
        pass
