"""What a render costs the server (issue 32): CPU by part and bytes on the
wire, counted from the render's start, so that loading the store, making
the statistics and waiting for tracers do not weigh on the cost per photon.

The parts are CPU seconds of the thread that runs them (`time.thread_time`,
a clock read on entry and exit, cheap beside the work they time):

- making photon jobs (on the message loop's thread): emission, start
  chunks, routing into job messages and encoding them;
- held deposits (the loop's thread too): adding a results message's
  deposits, and releasing a batch of them, re-culled to their own jobs'
  boxes;
- statistics updates (their own thread): applying hit points and batches
  of photons. The kernels' parallel workers run on threads of their own,
  so that share of the updates counts in neither part: with zmq's I/O
  threads, it is what is left of the process's CPU besides the loop's and
  the statistics thread's.
"""
from __future__ import annotations

import functools
import time

# A mark's fields: what is taken at the start and at the end.
FIELDS = ("cpu_s", "loop_cpu_s", "job_making_cpu_s", "held_cpu_s", "statistics_cpu_s",
          "bytes_in", "bytes_out")


def thread_cpu(counter: str):
    """A method decorator: the calling thread's CPU in the method is added
    to the float attribute `counter` of its object."""
    def wrap(method):
        @functools.wraps(method)
        def timed(self, *args, **kwargs):
            t0 = time.thread_time()
            try:
                return method(self, *args, **kwargs)
            finally:
                setattr(self, counter, getattr(self, counter) + time.thread_time() - t0)
        return timed
    return wrap


def mark(node) -> dict:
    """The server's counters now. Call it on the message loop's thread:
    `loop_cpu_s` is the calling thread's CPU."""
    return {"cpu_s": time.process_time(), "loop_cpu_s": time.thread_time(),
            "job_making_cpu_s": node.state.job_making_cpu_s + node.job_encoding_cpu_s,
            "held_cpu_s": node.state.held.cpu_s, "statistics_cpu_s": node.statistics.update_cpu_s,
            "bytes_in": node.bytes_in, "bytes_out": node.bytes_out}


def since(start: dict | None, end: dict) -> dict | None:
    """What the render cost from `start` to `end` (None: it never started)."""
    if start is None:
        return None
    return {k: round(end[k] - start[k], 6) if isinstance(end[k], float) else end[k] - start[k]
            for k in FIELDS}
