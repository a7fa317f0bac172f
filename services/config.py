"""Settings of the `server` and `worker` roles: one table of options, read
from flags, then the environment (DOSPPM_<NAME>), then a TOML file
(`--config`, table [server] or [worker]), then the defaults. Unknown keys
in the file are errors naming the file and key."""
from __future__ import annotations

import argparse
import os
import sys
import tomllib
from dataclasses import dataclass


@dataclass(frozen=True)
class Option:
    name: str          # flag without dashes, underscores for dashes
    type: type
    default: object
    help: str


def _opt(name, type_, default, help_):
    return Option(name, type_, default, help_)


RENDER = (
    _opt("time", float, None, "stop after S seconds of rendering (default 30 if no other limit)"),
    _opt("photons", float, None, "stop once N photons are emitted"),
    _opt("iterations", int, None, "stop after K eye iterations"),
    _opt("out", str, "out.exr", "output EXR (a PNG preview beside it)"),
    _opt("seed", int, 0, "random seed"),
    _opt("gather", str, "grid", "statistics gather: grid or hash"),
    _opt("alpha", float, 0.7, "radius reduction (eqs. 1-2)"),
    _opt("radius", float, None, "initial radius (default: from scene and pixel size)"),
    _opt("max_depth", int, 10, "surfaces a path may hit"),
    _opt("photons_per_iteration", int, 100_000, "photons between eye iterations"),
    _opt("photons_per_job", int, 1024, "photons per photon job"),
    _opt("photon_batch", int, 1_000_000, "deposits per statistics update (server batching)"),
    _opt("width", int, None, "image width override"),
    _opt("height", int, None, "image height override"),
    _opt("threads", int, os.cpu_count() or 1, "threads for the statistics update"),
    _opt("budget", str, None, "chunk memory budget when subdividing (default 512MiB)"),
    _opt("chunks", int, None, "force this many chunks"),
    _opt("store_cache", str, None, "where chunk stores made on the fly are kept"),
    _opt("exposure", float, 0.0, "PNG preview exposure in stops"),
    _opt("log", str, None, "append JSON-lines progress records here"),
)
# The paper's optimisations, each of which can be switched off (Figure 15).
OPTIMISATIONS = (
    _opt("cull", bool, True, "cull photons against the hit-point box (§4.3)"),
    _opt("concurrent", bool, True, "trace photons and eye rays at the same time (§3.3); "
         "--no-concurrent alternates them"),
    _opt("client_batching", bool, True, "tracers coalesce packages per chunk (§4.3)"),
)
SERVER = RENDER + OPTIMISATIONS + (
    _opt("bind", str, "tcp://127.0.0.1:5555", "ZeroMQ endpoint tracers connect to"),
    _opt("http", str, "127.0.0.1:8080", "status page HOST:PORT, or 'off'"),
    _opt("min_tracers", int, 1, "tracers to wait for before rendering"),
    _opt("min_photon_jobs", int, 1000, "photon jobs kept in flight (the paper's 1k)"),
    _opt("snapshot_interval", float, 60.0, "write the image every S seconds"),
    _opt("drain_timeout", float, 60.0, "at the end, wait this long for jobs in flight"),
    _opt("checkpoint", str, None, "checkpoint directory (default: OUT's name + '.checkpoint')"),
    _opt("checkpoint_interval", float, 60.0, "seconds between checkpoints; 0: none"),
    _opt("resume", str, None, "continue the render saved in this checkpoint directory"),
    _opt("curve_secret", str, None, "this server's CURVE key file (dosppm keys): encrypt and authenticate"),
    _opt("curve_clients", str, None, "directory of the public key files of the tracers to admit"),
    _opt("tracer_timeout", float, 10.0, "drop a tracer silent this long (its jobs are re-emitted); "
         "raise it for chunks that take longer than this to load"),
)
WORKER = (
    _opt("server", str, "tcp://127.0.0.1:5555", "the server's endpoint"),
    _opt("bind", str, "tcp://127.0.0.1:*", "endpoint for portal packages from other tracers"),
    _opt("advertise", str, None, "address other tracers reach this one at when binding 0.0.0.0; 'auto': "
         "this host's address on the route to the server"),
    _opt("store", str, None, "a local copy of the chunk store (else chunks are fetched)"),
    _opt("cache_dir", str, None, "where fetched chunks are kept"),
    _opt("memory", str, None, "resident chunk memory, e.g. 4GiB (default: all its chunks)"),
    _opt("threads", int, os.cpu_count() or 1, "tracing threads"),
    _opt("id", str, None, "tracer id (default host-pid-random)"),
    _opt("retry", float, 60.0, "keep trying to reach the server this long, in seconds"),
    _opt("curve_secret", str, None, "this tracer's CURVE key file (dosppm keys)"),
    _opt("curve_server_key", str, None, "the server's public key file"),
    _opt("curve_clients", str, None, "directory of the public key files of the tracers (its peers)"),
)


class ConfigError(ValueError):
    pass


def _add(p: argparse.ArgumentParser, options) -> None:
    for o in options:
        flag = "--" + o.name.replace("_", "-")
        if o.type is bool:
            p.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=o.help)
        else:
            p.add_argument(flag, type=o.type, default=None, help=o.help)
    p.add_argument("--config", help="TOML file with these settings")
    p.add_argument("--quiet", action="store_true")


def resolve(args, role: str, options, environ=os.environ) -> dict:
    """{name: value}: flag, then DOSPPM_<NAME>, then the file's [role] table,
    then the default."""
    table = _read_table(args.config, role, {o.name for o in options}) if args.config else {}
    out = {}
    for o in options:
        flag, env = getattr(args, o.name), environ.get("DOSPPM_" + o.name.upper())
        if flag is not None:
            out[o.name] = flag
        elif env is not None:
            out[o.name] = _convert(o, env, f"environment DOSPPM_{o.name.upper()}")
        elif o.name in table:
            out[o.name] = _convert(o, table[o.name], f"{args.config}: [{role}].{o.name}")
        else:
            out[o.name] = o.default
    return out


def _convert(o: Option, value, where: str):
    if o.type is bool:
        text = str(value).strip().lower()
        if isinstance(value, bool) or text in ("1", "true", "yes", "on", "0", "false", "no", "off"):
            return value if isinstance(value, bool) else text in ("1", "true", "yes", "on")
        raise ConfigError(f"{where}: expected true or false, got {value!r}")
    try:
        return o.type(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected {o.type.__name__}, got {value!r}") from None


def _read_table(path: str, role: str, known: set) -> dict:
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except OSError as e:
        raise ConfigError(f"{path}: cannot read: {e.strerror}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None
    table = doc.get(role, {})
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [{role}] must be a table")
    unknown = sorted(set(table) - known)
    if unknown:
        raise ConfigError(f"{path}: [{role}].{unknown[0]}: unknown setting")
    return table


def add_server_parser(sub) -> None:
    from dosppm_core.scene import builtin
    p = sub.add_parser("server", help="run the render server (tracers join with `dosppm worker`)")
    p.add_argument("scene", nargs="?", default=builtin.DEFAULT,
                   help="built-in scene, scene file or chunk store")
    _add(p, SERVER)
    p.set_defaults(func=cmd_server)


def add_worker_parser(sub) -> None:
    p = sub.add_parser("worker", help="run a tracer that joins a render server")
    _add(p, WORKER)
    p.set_defaults(func=cmd_worker)


def _resolve_or_say(args, role: str, options) -> dict | None:
    try:
        return resolve(args, role, options)
    except ConfigError as e:
        print(f"dosppm: error: {e}", file=sys.stderr)
        return None


def cmd_server(args) -> int:
    from services.local import serve
    values = _resolve_or_say(args, "server", SERVER)
    return 2 if values is None else serve(args.scene, values, quiet=args.quiet)


def cmd_worker(args) -> int:
    from services.local import work
    values = _resolve_or_say(args, "worker", WORKER)
    return 2 if values is None else work(values, quiet=args.quiet)


def add_keys_parser(sub) -> None:
    p = sub.add_parser("keys", help="make CURVE key pairs for the server and tracers")
    p.add_argument("names", nargs="+", help="one key pair per name, e.g. server tracer1 tracer2")
    p.add_argument("--out", default="keys", help="directory for NAME.key (public) and NAME.key_secret")
    p.set_defaults(func=cmd_keys)


def cmd_keys(args) -> int:
    from services import wire
    for name in args.names:
        public, secret = wire.make_keys(args.out, name)
        print(f"{name}: public {public}, secret {secret}")
    print("server: --curve-secret keys/server.key_secret --curve-clients DIR-with-the-tracers'-NAME.key; "
          "tracer: --curve-secret keys/NAME.key_secret --curve-server-key keys/server.key "
          "--curve-clients the same DIR")
    return 0
