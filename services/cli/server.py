"""`dosppm server`: run the render server; tracers join it with `dosppm worker`.

    dosppm server SCENE --bind tcp://0.0.0.0:5555 --http 0.0.0.0:8080 --min-tracers 4

Settings come from flags, then DOSPPM_<FLAG>, then table [server] of the
`--config` TOML file, then the defaults (`services.config.SERVER`).
"""
from __future__ import annotations

from dosppm_core.scene import builtin
from services import config
from services.local import run_server


def add_parser(sub) -> None:
    p = sub.add_parser("server", help="run the render server (tracers join with `dosppm worker`)")
    p.add_argument("scene", nargs="?", default=builtin.DEFAULT,
                   help="built-in scene, scene file or chunk store")
    config.add_role_options(p, config.SERVER)
    config.add_scene_parameters(p)
    p.set_defaults(func=run)


def run(args) -> int:
    values = {**config.resolve(args, "server", config.SERVER), "define": config.scene_parameters(args)}
    return run_server(args.scene, values, quiet=args.quiet)
