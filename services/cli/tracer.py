"""`dosppm worker`: start a tracer that joins a render server.

    dosppm worker --server tcp://HOST:5555 --bind tcp://0.0.0.0:5600 --advertise auto

The command keeps its name; the role it starts is a tracer. Settings come
from flags, then DOSPPM_<FLAG>, then table [tracer] of the `--config` TOML
file, then the defaults (`services.config.TRACER`).
"""
from __future__ import annotations

from services import config
from services.local import run_tracer


def add_parser(sub) -> None:
    p = sub.add_parser("worker", help="start a tracer that joins a render server",
                       description="Start a tracer: it loads (or fetches) the chunks the server "
                                   "assigns it and traces their jobs until the render ends.")
    config.add_role_options(p, config.TRACER)
    p.set_defaults(func=run)


def run(args) -> int:
    return run_tracer(config.resolve(args, "tracer", config.TRACER), quiet=args.quiet)
