"""Charts of `dosppm evaluate` (matplotlib, the `bench` extra): per scene,
relMSE against render time on log-log axes, one line per method, and an
image strip of each method at the full budget beside the reference."""
from __future__ import annotations

import math
import os

import matplotlib

matplotlib.use("Agg")   # files only, no display
import matplotlib.pyplot as plt  # noqa: E402

from dosppm_core.film import tonemap_srgb8  # noqa: E402


def write_charts(ev, out_dir: str) -> list[str]:
    paths = []
    for scene in dict.fromkeys(s.scene for s in ev.samples):
        paths.append(_error_chart(ev, scene, os.path.join(out_dir, f"error-{scene}.png")))
        if (scene, "reference") in ev.images:      # not for scenes carried over unrendered
            paths.append(_strip(ev, scene, os.path.join(out_dir, f"strip-{scene}.png")))
    return paths


def _error_chart(ev, scene: str, path: str) -> str:
    fig, ax = plt.subplots(figsize=(6.0, 4.2), dpi=110)
    for method in dict.fromkeys(s.method for s in ev.samples if s.scene == scene):
        pts = sorted((s.seconds, s.relmse) for s in ev.samples
                     if s.scene == scene and s.method == method and s.finite
                     and math.isfinite(s.relmse) and s.relmse > 0 and s.seconds > 0)
        if pts:
            ax.plot(*zip(*pts), marker="o", markersize=3, linewidth=1.2, label=method)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("render time (s)")
    ax.set_ylabel("relMSE to reference")
    ax.set_title(f"{scene}\nreference: {ev.references.get(scene, '?')}", fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _strip(ev, scene: str, path: str) -> str:
    names = ["reference"] + [m for (s, m) in ev.images if s == scene and m != "reference"]
    fig, axes = plt.subplots(1, len(names), figsize=(1.6 * len(names), 1.9), dpi=110)
    for ax, name in zip(axes if len(names) > 1 else [axes], names):
        ax.imshow(tonemap_srgb8(ev.images[(scene, name)]), interpolation="nearest")
        ax.set_title(name, fontsize=6)
        ax.axis("off")
    fig.suptitle(f"{scene} at {ev.budget_s:g} s", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
