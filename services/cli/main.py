"""The `dosppm` command line: the library's commands (render, scenes,
subdivide, bench, reference, compare) plus the service's roles.

    dosppm render [SCENE] [--tracers N]   server + N tracers on this machine (default)
    dosppm render SCENE --mode sppm|osppm the single-process renderers
    dosppm server SCENE --bind tcp://0.0.0.0:5555 --http 0.0.0.0:8080
    dosppm worker --server tcp://HOST:5555

DOSPPM_LOG_LEVEL=info (or debug) shows the roles' log lines.

Settings for `server` and `worker` come from flags, then the environment
(DOSPPM_<FLAG>, e.g. DOSPPM_SERVER=tcp://10.0.0.1:5555), then a TOML file
(`--config`, table [server] or [worker]), then the defaults: a flag beats
the environment, which beats the file. The server hands its render
settings to every tracer at registration.
"""
from __future__ import annotations

import argparse
import logging
import os
import sys

from services.cli import render as core

from services import config


def add_service_render_arguments(render: argparse.ArgumentParser) -> None:
    g = render.add_argument_group("the render service (default mode)")
    g.add_argument("--mode", choices=("dosppm", "sppm", "osppm"), default="dosppm",
                   help="dosppm: a server and tracer processes on this machine (default); "
                        "sppm: one process, whole scene; osppm: one process, chunk by chunk")
    g.add_argument("--tracers", type=int, help="tracer processes (default: one per core)")
    g.add_argument("--http", default="127.0.0.1:0", metavar="HOST:PORT",
                   help="status page address (default: loopback, any free port); 'off' for none")
    g.add_argument("--min-photon-jobs", type=int, default=1000,
                   help="photon jobs kept in flight (the paper's 1k)")
    g.add_argument("--photons-per-job", type=int, default=1024)
    g.add_argument("--snapshot-interval", type=float, default=60.0, metavar="S",
                   help="write the image every S seconds while rendering")
    g.add_argument("--checkpoint", metavar="DIR", help="checkpoint directory (default: OUT's name + "
                   "'.checkpoint')")
    g.add_argument("--checkpoint-interval", type=float, default=60.0, metavar="S",
                   help="seconds between checkpoints of the pixel statistics; 0: none")
    g.add_argument("--resume", metavar="DIR", help="continue the render saved in this checkpoint")
    g.add_argument("--tracer-timeout", type=float, default=10.0, metavar="S",
                   help="drop a tracer silent for S seconds; its jobs are re-emitted")
    for o in config.OPTIMISATIONS:
        g.add_argument("--" + o.name.replace("_", "-"), action=argparse.BooleanOptionalAction,
                       default=True, help=o.help)
    render.set_defaults(func=cmd_render)


def cmd_render(args) -> int:
    if args.mode == "sppm":
        if args.budget or args.chunks:
            return core._error("--mode sppm renders the whole scene: drop --budget/--chunks")
        return core.cmd_render(args)
    if args.mode == "osppm":
        if not (args.budget or args.chunks):
            args.budget = "512MiB"
        return core.cmd_render(args)
    from services.local import render_local
    return render_local(args)


def build_parser() -> argparse.ArgumentParser:
    parser, sub = core.make_parser()
    add_service_render_arguments(sub.choices["render"])
    config.add_server_parser(sub)
    config.add_worker_parser(sub)
    config.add_keys_parser(sub)
    return parser


def main(argv=None) -> int:
    logging.basicConfig(level=os.environ.get("DOSPPM_LOG_LEVEL", "WARNING").upper(),
                        format="dosppm %(name)s: %(levelname)s: %(message)s")
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
