"""`ServerState`'s collection of the light eye paths saw (issue 32; the
tracers' side is services/tracer/light.py). Tracers hold each eye
iteration's light per pixel; once `batch` iterations are complete (every
path's credit back, so all of their light is held), the server asks every
tracer for them in one round and applies the summed answers as one update:
the iterations' emission, and their count in the image's average. At the
end of a render, with no eye iteration left in flight, it asks for the
rest.

Exactly once: a round is applied when every tracer asked has answered,
and a tracer answers a round once (it forgets the light it sent). A lost
tracer held part of every iteration not yet applied, so those are
discarded whole (the round under way and the iterations waiting for one),
and tracers drop their parts when a later round passes them. Which
iterations count never depends on what they saw.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dosppm_core.sppm.statistics import add_rows
from services.server.records import Update
from services.wire import Out


@dataclass
class LightRound:
    index: int
    iterations: list
    waiting: set
    asked_s: float
    parts: list = field(default_factory=list)     # (pixels, rgb) of each answer


class LightRounds:
    """Pure: complete iterations in, rounds to ask and rounds answered out."""

    def __init__(self, batch: int):
        self.batch = max(1, int(batch))
        self.due: list[int] = []            # complete, their light still at the tracers
        self.round: LightRound | None = None
        self.next_round = 0
        self.counters = {"light_rounds": 0, "eye_iterations_light_discarded": 0}

    def complete(self, eye_iteration: int) -> None:
        self.due.append(int(eye_iteration))

    def start(self, tracers, now: float, final: bool) -> LightRound | None:
        """A round for the due iterations, if none is under way and
        `batch` are due (any, when `final`)."""
        if self.round is not None or not self.due or not tracers or (len(self.due) < self.batch and not final):
            return None
        self.round = LightRound(self.next_round, self.due, set(tracers), now)
        self.next_round += 1
        self.due = []
        return self.round

    def answer(self, tid: str, msg) -> LightRound | None:
        """A tracer's `eye_light`; the round once every answer is in (None
        while some are missing, or for a stale answer)."""
        r = self.round
        if r is None or msg.round != r.index or tid not in r.waiting:
            return None
        r.waiting.discard(tid)
        r.parts.append((msg.pixels, msg.rgb))
        if r.waiting:
            return None
        self.round = None
        self.counters["light_rounds"] += 1
        return r

    def discard(self) -> None:
        """A tracer lost or restarted: every iteration not applied is."""
        lost = len(self.due) + (len(self.round.iterations) if self.round else 0)
        self.due, self.round = [], None
        self.counters["eye_iterations_light_discarded"] += lost

    def waiting_since(self, now: float) -> float:
        return now - self.round.asked_s if self.round is not None else 0.0

    @property
    def drained(self) -> bool:
        return not self.due and self.round is None


def summed(parts: list, n_pixels: int) -> np.ndarray:
    """A round's answers added up per pixel, (n_pixels, 3) float64."""
    out = np.zeros((n_pixels, 3))
    for pixels, rgb in parts:
        add_rows(out, pixels, rgb)      # pixels are distinct within an answer (the wire checks)
    return out


class EyeLightMixin:
    light: LightRounds

    def _init_light(self) -> None:
        self.light = LightRounds(self.hit_point_stride)

    def light_settings(self) -> dict:
        return {"hold_light": True}

    def _ask_light(self) -> list[Out]:
        """A round, when one is due: while rendering, every `batch` eye
        iterations; draining, once no eye iteration is in flight."""
        final = not self.emitting and not self.eyes
        r = self.light.start(self.tracers, self._now, final)
        if r is None:
            return []
        ids = np.array(r.iterations, np.int64)
        return [Out(tid, "light_request", dict(round=r.index, eye_iterations=ids)) for tid in sorted(r.waiting)]

    def _on_eye_light_message(self, t, msg, now: float) -> list[Out]:
        p = msg.pixels
        if len(p) and p[-1] >= self.n_pixels:
            return [Out(t.id, "error", dict(reason=f"eye_light: field 'pixels' reaches {int(p[-1])}, "
                                                   f"the image has {self.n_pixels}", about="eye_light"))]
        r = self.light.answer(t.id, msg)
        if r is not None:
            self.updates.append(Update("light", light=summed(r.parts, self.n_pixels),
                                       light_iterations=len(r.iterations)))
        return []
