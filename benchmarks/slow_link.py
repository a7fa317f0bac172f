"""Issue 32 step 6: what one server feeds through a 1 Gbit/s link.

The replay harness (harness/replay.py: a real server, fed at
full speed by synthetic tracers that answer photon jobs with recorded
results) runs across network namespaces, the server on its own host whose
link is capped at `--rate` each way (`tc tbf`, harness/netns.py), with
the paper's wire format (`--gather-at server`: every deposit goes to the
server) and with the gather at the tracers (per-hit-point sums by epoch),
alternated run by run.

For each it reports the photons the server applied per second, and the
two ceilings: the link's (its rate over the bytes per photon of the busier
direction) and the server's CPU (photons per second of server CPU). A run
near the lower ceiling was held by that side; one far below both, by the
tracers. The headline is the ratio of the photons per second applied with
the gather at the tracers to what the link allows the paper's wire
format, and the same ratio for that mode's own ceiling. The synthetic tracers replay recorded epochs and answer photon
job messages at once (replay.py's `replay_epochs` and `replay_emission`),
so neither their gather nor their emission costs anything: two of them
making and tracing photons for real on the server's two cores made 2.7M
photons/s, far below both of the server's ceilings. Their eye rays are
still traced for real (the hit points must be right), so an eye
iteration starts every `--photons-per-iteration` photons, 4M, not the
default 1.5 a pixel: at 15M photons/s that would be ten million eye rays
a second, the work of a cluster, not of two synthetic tracers.

The gather at the tracers runs twice: at the paper's statistics batch
(1M photons) and at `--photon-batch` (8M). Gathering at the tracers an
epoch is a batch, and each epoch's hit points and sums cross the link
once and make a round trip; at 1M those round trips, not the link's rate,
hold the photons (the link stays under a third used). Photons per second
are quoted steady, the median of the status history's rates over the
run's second half (the synthetic tracers' first steps and epochs are
real work), and over the whole run. (At
`--rate 1e8` neither figure is clean: each epoch's hit points, 7 MB to
two tracers, take 0.6 s to cross, and the epochs' round trips, not the
average rate, hold the photons.)

    python benchmarks/slow_link.py [--rate 1e9] [--seconds 30]
        [--photons-per-iteration 4000000] [--photon-batch 8000000] [--repeats 3]

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
from services.server.epochs import MOST_MERGED  # noqa: E402

PREFIX = f"dosppm-link-{os.getpid()}"
SUBNET = f"10.216.{os.getpid() % 250 + 1}"
HOSTS = {"server": f"{SUBNET}.1", "t1": f"{SUBNET}.11", "t2": f"{SUBNET}.12"}
PAPER_BATCH = 1_000_000     # the paper's statistics batch (§4.3)


def modes(args) -> dict:
    """Row name -> (--gather-at, --photon-batch, --batch-growth): the
    paper's format, and the gather at the tracers at the paper's batch, with
    the epochs fixed (growth 1) and merged when the round trips hold them
    (the default), and at `args.photon_batch`."""
    return {"server": ("server", PAPER_BATCH, 1), "tracers, fixed batch": ("tracers", PAPER_BATCH, 1),
            "tracers": ("tracers", PAPER_BATCH, MOST_MERGED),
            "tracers, large batch": ("tracers", args.photon_batch, MOST_MERGED)}
NEAR_CEILING = 0.7      # a run applying less than this share of its lower ceiling was held by the tracers


def one_run(hosts: dict, mode: tuple, args, work: str, per_core: float) -> dict:
    gather_at, batch, growth = mode
    rx0, tx0 = link_bytes(PREFIX, "server")
    t0 = time.monotonic()
    extra = ("--gather-at", gather_at, "--photons-per-iteration", str(args.photons_per_iteration),
             "--photon-batch", str(batch), "--batch-growth", str(growth))
    s = replay.run(args.scene, 2, args.seconds, work, extra, replay_epochs=True,
                   replay_emission=True, hosts={"server": hosts["server"], "tracers": [hosts["t1"][0], hosts["t2"][0]]})
    wall = time.monotonic() - t0
    rx1, tx1 = link_bytes(PREFIX, "server")
    f = replay.figures(s, per_core)
    # The link carries each way at its rate: the busier direction limits.
    link_photons = args.rate / 8 / max(f["bytes_in_per_photon"], f["bytes_out_per_photon"], 1e-9)
    return dict(f, gather_at=gather_at, photon_batch=batch, batch_growth=growth,
                # The whole process's traffic on the link (start-up included),
                # as a check that the cap held: never above the rate.
                link_in_bit_s=8 * (rx1 - rx0) / wall, link_out_bit_s=8 * (tx1 - tx0) / wall,
                link_ceiling_photons_per_s=link_photons,
                cpu_ceiling_photons_per_s=f["photons_per_server_cpu_s"],
                limited_by=_limit(f["steady_photons_per_s"], link_photons, f["photons_per_server_cpu_s"]))


def _limit(applied: float, link: float, cpu: float) -> str:
    """Which side held the photons applied: the lower ceiling when the run
    came near it, else the tracers (two synthetic ones sharing this
    machine's cores with the server could not make more)."""
    if applied < NEAR_CEILING * min(link, cpu):
        return "tracers"
    return "link" if link < cpu else "server CPU"


def run(args) -> dict:
    runs = {m: [] for m in modes(args)}
    with lan(PREFIX, HOSTS) as hosts, tempfile.TemporaryDirectory(prefix="dosppm-link-") as work:
        limit_rate(PREFIX, "server", args.rate)
        for _ in range(args.repeats):
            per_core = replay.tracer_rate(args.scene)
            for m, mode in modes(args).items():   # alternated: drift hits all alike
                runs[m].append(one_run(hosts, mode, args, work, per_core))
    rows = {m: median_of(r) for m, r in runs.items()}
    for r in rows.values():
        r["limited_by"] = r["samples"][0]["limited_by"] if len({s["limited_by"] for s in r["samples"]}) == 1 \
            else "mixed"
    # What the link allows the paper's wire format: every deposit in.
    paper_link = args.rate / 8 / rows["server"]["bytes_in_per_photon"]
    return {"scene": args.scene, "rate_bit_s": args.rate, "seconds": args.seconds,
            "photons_per_iteration": args.photons_per_iteration, "rows": rows,
            "paper_link_photons_per_s": paper_link,
            "over_paper_link": {m: _over(r, paper_link) for m, r in rows.items() if m != "server"}}


def _over(row: dict, paper_link: float) -> dict:
    """A row's photons per second over what the link allows the paper's
    format: steady (past the start), over the whole run, and its own
    ceiling's (the lower of the link's and the server CPU's)."""
    return {"steady": row["steady_photons_per_s"] / paper_link,
            "whole_run": row["photons_per_s"] / paper_link,
            "ceiling": min(row["link_ceiling_photons_per_s"], row["cpu_ceiling_photons_per_s"]) / paper_link}


def report(res: dict) -> str:
    gbit = res["rate_bit_s"] / 1e9
    lines = [f"Slow link: the server's link capped at {gbit:g} Gbit/s each way (tc tbf), 2 synthetic tracers on "
             f"their own hosts, {res['scene']}, {res['seconds']:.0f} s a run, medians of "
             f"{next(iter(res['rows'].values()))['repeats']}, an eye iteration every "
             f"{res['photons_per_iteration']:,} photons. Photons/s: steady (the run's second half) / "
             f"whole run.", "",
             "| gather at | statistics batch | epochs merged, at most | photons/s applied | bytes in / out per photon "
             "| link ceiling (photons/s) | server CPU ceiling (photons/s) | limited by | link in / out (Mbit/s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for m, r in res["rows"].items():
        merged = "-" if r["gather_at"] == "server" else \
            f"{r.get('epochs_merged_most', 1)} of {r.get('batch_growth', 1)}"
        lines.append(f"| {r['gather_at']} | {r['photon_batch']:,} | {merged} | {r['steady_photons_per_s']:,.0f} / "
                     f"{r['photons_per_s']:,.0f} | {r['bytes_in_per_photon']:.1f} / "
                     f"{r['bytes_out_per_photon']:.1f} | {r['link_ceiling_photons_per_s']:,.0f} "
                     f"| {r['cpu_ceiling_photons_per_s']:,.0f} | {r['limited_by']} "
                     f"| {r['link_in_bit_s'] / 1e6:.0f} / {r['link_out_bit_s'] / 1e6:.0f} |")
    lines += ["", f"The link allows the paper's wire format {res['paper_link_photons_per_s']:,.0f} photons/s "
              "(issue 32 asks 10x that). Gathering at the tracers, the server applied:"]
    for m, o in res["over_paper_link"].items():
        r = res["rows"][m]
        growth = "fixed" if r.get("batch_growth", 1) == 1 else f"merging up to {r['batch_growth']} epochs"
        lines.append(f"- statistics batch {r['photon_batch']:,}, {growth}: {o['steady']:.1f}x steady "
                     f"({o['whole_run']:.1f}x over the whole run), limited by {r['limited_by']}; "
                     f"its own ceiling is {o['ceiling']:.1f}x")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="cornell-glass")
    p.add_argument("--rate", type=float, default=1e9, help="the server's link, bit/s each way")
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--photons-per-iteration", type=int, default=4_000_000,
                   help="the server's: photons between eye iterations (their rays are traced for real)")
    p.add_argument("--photon-batch", type=int, default=8_000_000,
                   help="the large batch row's --photon-batch: photons per statistics update, so per epoch "
                        "gathering at the tracers (the other rows: the paper's 1M)")
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
