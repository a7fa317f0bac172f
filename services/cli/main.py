"""The `dosppm` command: render scenes in one process or with the render
service, run the service's roles, and the tools around them.

    dosppm render [SCENE] [--tracers N]   a server + N tracers on this machine (default)
    dosppm render SCENE --mode sppm|osppm the single-process renderers
    dosppm server SCENE --bind tcp://0.0.0.0:5555 --http 0.0.0.0:8080
    dosppm worker --server tcp://HOST:5555   a tracer joining that server

DOSPPM_LOG_LEVEL=info (or debug) shows the roles' log lines.

Settings for `server` and `worker` come from flags, then the environment
(DOSPPM_<FLAG>, e.g. DOSPPM_SERVER=tcp://10.0.0.1:5555), then a TOML file
(`--config`, table [server] or [tracer]), then the defaults: a flag beats
the environment, which beats the file. The server hands its render
settings to every tracer at registration.
"""
from __future__ import annotations

import argparse
import atexit
import logging
import os

from dosppm_core.malloc import return_large_blocks
from services import transport
from services.cli import harness_verbs, keys, render, scenes, server, subdivide, tracer
from services.cli.errors import Parser, fail
from services.config import ConfigError

# Each subcommand: `add_parser(sub)` registers it, with its `run`. The
# harness's verbs are doors that load harness/ only when one of them runs.
COMMANDS = (render, scenes, subdivide, *harness_verbs.VERBS, server, tracer, keys)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="dosppm", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    return parser


def main(argv=None) -> int:
    return_large_blocks()           # before any chunk is loaded (dosppm_core/malloc.py)
    # At exit, before the interpreter frees the arrays zmq sends from
    # (in-process callers, such as tests, keep the context until then).
    atexit.register(transport.finish_process)
    logging.basicConfig(level=os.environ.get("DOSPPM_LOG_LEVEL", "WARNING").upper(),
                        format="dosppm %(name)s: %(levelname)s: %(message)s")
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ConfigError as e:    # a setting from the environment or a --config file
        return fail(str(e))
