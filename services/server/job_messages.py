"""Eye job messages being filled by the server: an eye iteration's tiles
are routed to their start chunks' tracers in parts, and one message goes
out per (tracer, chunk)."""
from __future__ import annotations

import numpy as np

from dosppm_core.jobs import RayBatch


class JobMessages(dict):
    """(tracer id, chunk) -> [(batch, credit share)] of job messages being filled."""

    def add(self, key: tuple, part: RayBatch, share: tuple) -> None:
        self.setdefault(key, []).append((part, share))

    def take(self, key: tuple) -> dict:
        return _package(self.pop(key))


def _package(parts: list) -> dict:
    """A job message's batch and credit from its (batch, credit share) parts."""
    return dict(batch=RayBatch.concat([b for b, _ in parts]),
                credit_job=np.concatenate([c[0] for _, c in parts]),
                credit_exp=np.concatenate([c[1] for _, c in parts]))
