"""Issue 32 step 6: what one server feeds through a 1 Gbit/s link.

The replay harness (harness/replay.py: a real server, fed at
full speed by synthetic tracers that answer photon jobs with recorded
results) runs across network namespaces, the server on its own host whose
link is capped at `--rate` each way (`tc tbf`, harness/netns.py),
once with the paper's wire format (`--gather-at server`: every deposit goes
to the server) and once with the gather at the tracers (per-hit-point sums
by epoch), alternated run by run.

For each it reports the photons the server applied per second, and the
two ceilings: the link's (its rate over the bytes per photon of the busier
direction: into the server with the paper's format, out of it, the hit
points to every tracer, with the gather at the tracers) and the server's
CPU (photons per second of server CPU). The
smaller ceiling is the side that limits. The headline is the ratio of the
photons per second applied with the gather at the tracers to what the link
allows the paper's wire format, and the same ratio for that mode's own
ceiling. The synthetic tracers replay recorded epochs (replay.py's
`replay_epochs`), so their gather costs nothing; still, two of them
sharing two cores with the server make about 3M photons/s, below the
server's ceiling at 1 Gbit/s, so "limited by" names the tracers. (At
`--rate 1e8` neither figure is clean: each epoch's hit points, 7 MB to
two tracers, take 0.6 s to cross, and the epochs' round trips, not the
average rate, hold the photons.)

    python benchmarks/slow_link.py [--rate 1e9] [--seconds 15] [--repeats 3]

Needs root and iproute2 (network namespaces); writes
benchmarks/results/slow-link.json.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from harness import replay  # noqa: E402
from harness.netns import NetnsUnavailable, lan, limit_rate, link_bytes  # noqa: E402
from harness.provenance import median_of, write_results  # noqa: E402

PREFIX = f"dosppm-link-{os.getpid()}"
SUBNET = f"10.216.{os.getpid() % 250 + 1}"
HOSTS = {"server": f"{SUBNET}.1", "t1": f"{SUBNET}.11", "t2": f"{SUBNET}.12"}
MODES = ("server", "tracers")
NEAR_CEILING = 0.7      # a run applying less than this share of its lower ceiling was held by the tracers


def one_run(hosts: dict, gather_at: str, args, work: str, per_core: float) -> dict:
    rx0, tx0 = link_bytes(PREFIX, "server")
    t0 = time.monotonic()
    s = replay.run(args.scene, 2, args.seconds, work, ("--gather-at", gather_at), replay_epochs=True,
                   hosts={"server": hosts["server"], "tracers": [hosts["t1"][0], hosts["t2"][0]]})
    wall = time.monotonic() - t0
    rx1, tx1 = link_bytes(PREFIX, "server")
    f = replay.figures(s, per_core)
    # The link carries each way at its rate: the busier direction limits.
    link_photons = args.rate / 8 / max(f["bytes_in_per_photon"], f["bytes_out_per_photon"], 1e-9)
    return dict(f, gather_at=gather_at,
                # The whole process's traffic on the link (start-up included),
                # as a check that the cap held: never above the rate.
                link_in_bit_s=8 * (rx1 - rx0) / wall, link_out_bit_s=8 * (tx1 - tx0) / wall,
                link_ceiling_photons_per_s=link_photons,
                cpu_ceiling_photons_per_s=f["photons_per_server_cpu_s"],
                limited_by=_limit(f["photons_per_s"], link_photons, f["photons_per_server_cpu_s"]))


def _limit(applied: float, link: float, cpu: float) -> str:
    """Which side held the photons applied: the lower ceiling when the run
    came near it, else the tracers (two synthetic ones sharing this
    machine's cores with the server could not make more)."""
    if applied < NEAR_CEILING * min(link, cpu):
        return "tracers"
    return "link" if link < cpu else "server CPU"


def run(args) -> dict:
    runs = {m: [] for m in MODES}
    with lan(PREFIX, HOSTS) as hosts, tempfile.TemporaryDirectory(prefix="dosppm-link-") as work:
        limit_rate(PREFIX, "server", args.rate)
        for _ in range(args.repeats):
            per_core = replay.tracer_rate(args.scene)
            for m in MODES:         # alternated: drift on a shared machine hits both alike
                runs[m].append(one_run(hosts, m, args, work, per_core))
    rows = {m: median_of(r) for m, r in runs.items()}
    for r in rows.values():
        r["limited_by"] = r["samples"][0]["limited_by"] if len({s["limited_by"] for s in r["samples"]}) == 1 \
            else "mixed"
    # What the link allows the paper's wire format: every deposit in.
    paper_link = args.rate / 8 / rows["server"]["bytes_in_per_photon"]
    t = rows["tracers"]
    return {"scene": args.scene, "rate_bit_s": args.rate, "seconds": args.seconds, "rows": rows,
            "paper_link_photons_per_s": paper_link,
            "tracers_over_paper_link": t["photons_per_s"] / paper_link,
            "tracers_ceiling_over_paper_link": min(t["link_ceiling_photons_per_s"],
                                                   t["cpu_ceiling_photons_per_s"]) / paper_link}


def report(res: dict) -> str:
    gbit = res["rate_bit_s"] / 1e9
    lines = [f"Slow link: the server's link capped at {gbit:g} Gbit/s each way (tc tbf), 2 synthetic tracers on "
             f"their own hosts, {res['scene']}, {res['seconds']:.0f} s a run, medians of "
             f"{next(iter(res['rows'].values()))['repeats']}.", "",
             "| gather at | photons/s applied | bytes in / out per photon | link ceiling (photons/s) "
             "| server CPU ceiling (photons/s) | limited by | link in / out (Mbit/s) |",
             "|---|---|---|---|---|---|---|"]
    for m, r in res["rows"].items():
        lines.append(f"| {m} | {r['photons_per_s']:,.0f} | {r['bytes_in_per_photon']:.1f} / "
                     f"{r['bytes_out_per_photon']:.1f} | {r['link_ceiling_photons_per_s']:,.0f} "
                     f"| {r['cpu_ceiling_photons_per_s']:,.0f} | {r['limited_by']} "
                     f"| {r['link_in_bit_s'] / 1e6:.0f} / {r['link_out_bit_s'] / 1e6:.0f} |")
    lines += ["", f"The link allows the paper's wire format {res['paper_link_photons_per_s']:,.0f} photons/s. "
              f"With the gather at the tracers the server applied {res['tracers_over_paper_link']:.2f}x that, "
              f"limited by {res['rows']['tracers']['limited_by']}; its own ceiling, the lower of the link's "
              f"and its CPU's, is {res['tracers_ceiling_over_paper_link']:.1f}x (issue 32 asks 10x)."]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="cornell-glass")
    p.add_argument("--rate", type=float, default=1e9, help="the server's link, bit/s each way")
    p.add_argument("--seconds", type=float, default=15.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "slow-link.json"))
    args = p.parse_args(argv)
    try:
        res = run(args)
    except NetnsUnavailable as e:
        print(f"slow_link: {e}", file=sys.stderr)
        return 2
    print(report(res))
    write_results(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
