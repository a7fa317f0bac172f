"""Plot benchmarks/results/osppm.json as the paper's Figure 11: photon and
hit-point throughput against the number of chunks, relative to c = 1.

    pip install '.[bench]' && python benchmarks/plot_osppm.py
"""
from __future__ import annotations

import json
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main() -> int:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    with open(os.path.join(ROOT, "benchmarks", "results", "osppm.json")) as f:
        data = json.load(f)
    rows = data["rows"] if isinstance(data, dict) else data     # older files: the rows alone
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, (key, title) in zip(axes, (("all", "every chunk resident"),
                                       ("two", "room for two chunks (active + prefetched)"))):
        for scene in dict.fromkeys(r["scene"] for r in rows):
            mine = [r for r in rows if r["scene"] == scene]
            base = mine[0]["all"]["photons_per_s"]
            ax.plot([r["chunks"] for r in mine], [r[key]["photons_per_s"] / base for r in mine],
                    marker="o", label=f"{scene}")
        ax.axhline(0.7, color="grey", linestyle=":", label="target at c = 8")
        ax.set_xscale("log", base=2)
        ax.set_xlabel("chunks c")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("OSPPM photons/s relative to c = 1")
    axes[0].legend()
    fig.suptitle("OSPPM throughput against chunk count (cf. Günther & Grosch, Figure 11)")
    fig.tight_layout()
    out = os.path.join(ROOT, "docs", "figures", "osppm-chunks.png")
    os.makedirs(os.path.dirname(out), exist_ok=True)
    fig.savefig(out, dpi=110)
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
