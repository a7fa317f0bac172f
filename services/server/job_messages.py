"""Job messages being filled by the server's emission: photon jobs are
routed to their start chunks' tracers in parts, and a message goes out per
(tracer, chunk) once it holds a message's worth of rays."""
from __future__ import annotations

import numpy as np

from dosppm_core.jobs import RayBatch


class JobMessages(dict):
    """(tracer id, chunk) -> [(batch, credit share)] of job messages being
    filled, with running ray counts (summing the parts again after every
    job made flushing quadratic: half the server's time at 300k photons/s)."""

    def __init__(self):
        super().__init__()
        self.rays: dict = {}

    def add(self, key: tuple, part: RayBatch, share: tuple) -> None:
        self.setdefault(key, []).append((part, share))
        self.rays[key] = self.rays.get(key, 0) + len(part)

    def keys_at(self, rays: int) -> list:
        return [k for k, n in self.rays.items() if n >= rays]

    def take(self, key: tuple) -> dict:
        del self.rays[key]
        return _package(self.pop(key))


def _package(parts: list) -> dict:
    """A job message's batch and credit from its (batch, credit share) parts."""
    return dict(batch=RayBatch.concat([b for b, _ in parts]),
                credit_job=np.concatenate([c[0] for _, c in parts]),
                credit_exp=np.concatenate([c[1] for _, c in parts]))
