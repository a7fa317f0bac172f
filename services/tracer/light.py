"""The light eye paths saw, held at the tracer until the server asks
(issue 32). Every eye iteration adds to each pixel the emission its paths
saw directly and the direct light its shadow rays carried: about one value
per pixel per iteration, 16 bytes on the wire, which at 1.5 photons per
pixel an iteration was 8 bytes into the server per photon by itself.
Held here per eye iteration and sent summed per pixel over several
iterations (`light_request`), each pixel crosses the wire once a round.

Exactly once: the server asks only for complete iterations (all their
paths' credit returned, so all their light is held here), names them, and
applies a round whole or not at all; iterations it will never ask for (a
lost tracer held part of them) are dropped here when a later round passes
them. Pure: arrays in, reply fields out.
"""
from __future__ import annotations

import numpy as np


class LightHold:
    def __init__(self):
        self.held: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
        self.counters = {"light_rounds": 0, "light_iterations_dropped": 0}

    def add(self, eye_iteration: int, pixels: np.ndarray, rgb: np.ndarray) -> None:
        if len(pixels):
            self.held.setdefault(int(eye_iteration), []).append((pixels, rgb))

    def clear(self) -> None:
        """Forget everything (a tracer welcomed again: the server discarded it all)."""
        self.held.clear()

    def reply(self, round_: int, eye_iterations: np.ndarray) -> dict:
        """The `eye_light` fields answering a `light_request`: the light
        held for `eye_iterations`, summed per pixel (pixels in increasing
        order), now forgotten; with every iteration before the last asked
        that was not asked (discarded by the server)."""
        asked = set(np.asarray(eye_iterations, np.int64).tolist())
        last = max(asked, default=-1)
        parts = []
        for e in [e for e in self.held if e <= last]:
            if e in asked:
                parts += self.held.pop(e)
            else:
                del self.held[e]
                self.counters["light_iterations_dropped"] += 1
        self.counters["light_rounds"] += 1
        pixels, rgb = summed(parts)
        return dict(round=int(round_), pixels=pixels, rgb=rgb)


def summed(parts: list) -> tuple[np.ndarray, np.ndarray]:
    """[(pixels, rgb)] summed per pixel: (distinct pixels i32, rgb f32),
    added in float64 before the one rounding to float32."""
    if not parts:
        return np.zeros(0, np.int32), np.zeros((0, 3), np.float32)
    pix = np.concatenate([p for p, _ in parts]).astype(np.int64)
    rgb = np.concatenate([c for _, c in parts]).astype(np.float64)
    pixels, row = np.unique(pix, return_inverse=True)
    out = np.stack([np.bincount(row, rgb[:, k], minlength=len(pixels)) for k in range(3)], axis=1)
    return pixels.astype(np.int32), out.astype(np.float32)
