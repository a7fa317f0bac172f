"""Settings of a render and of the service's roles: one table of options
with their defaults, read by the `render` flags and by the `server` and
`worker` (a tracer) commands.

The server and a tracer read each option from a flag, then the environment
(DOSPPM_<NAME>), then a TOML file (`--config`, table [server] or
[tracer]), then the default. Unknown keys in the file are errors naming the
file and key.

The render settings' defaults are the library's (`RenderSettings`), but for
the job sizes, which the service cuts finer (`SERVICE_JOB_SIZES`)."""
from __future__ import annotations

import argparse
import dataclasses
import math
import os
import re
import tomllib
from dataclasses import dataclass

from dosppm_core.settings import (DEFAULT_BUDGET_BYTES, DIRECT_MODES, SERVICE_JOB_SIZES, RenderSettings,
                                  GATHER_AT_TRACERS_PHOTONS_PER_JOB, service_job_sizes,
                                  default_store_cache, scene_settings)
from services.server.epochs import MOST_MERGED


@dataclass(frozen=True)
class Option:
    name: str          # flag without dashes, underscores for dashes
    type: type
    default: object
    help: str
    choices: tuple | None = None
    rule: str | None = None    # a key of RULES: what a value must be, wherever it comes from


class ConfigError(ValueError):
    pass


_LIBRARY = RenderSettings()
_SETTINGS_FIELDS = tuple(f.name for f in dataclasses.fields(RenderSettings))

# The command line traces on every core (the library's default, 2, suits
# tests and callers that share the machine).
THREADS = os.cpu_count() or 1
SECONDS = 30.0                  # a render's length when no limit is given
BUDGET_BYTES = DEFAULT_BUDGET_BYTES   # memory per chunk when a scene is subdivided on the fly


def _opt(name, type_, default, help_, choices=None, rule=None):
    return Option(name, type_, default, help_, choices, rule)


# What a numeric or address setting must be. Each returns None when the
# value is good, else what is wrong with it (a flag, DOSPPM_<NAME> or a
# TOML key: the same rule, the same words).
def _positive(v):
    return None if math.isfinite(v) and v > 0 else f"must be > 0, got {v:g}"


def _non_negative(v):
    return None if math.isfinite(v) and v >= 0 else f"must be >= 0, got {v:g}"


def _count(v):
    return None if v >= 1 else f"must be >= 1, got {v}"


def _open_unit(v):
    return None if 0 < v < 1 else f"must lie in (0, 1), got {v:g}"


def _finite(v):
    return None if math.isfinite(v) else f"must be a finite number, got {v:g}"


def _size(v):
    try:
        parse_bytes(v, "size")
    except ValueError as e:
        return str(e).removeprefix("size: ")
    return None


def _host_port(v):
    if v == "off":
        return None
    host, _, port = v.rpartition(":")
    return _port(port, v) if host else f"expected HOST:PORT or 'off', got {v!r}"


def _endpoint(v):
    m = re.fullmatch(r"(tcp)://([^:/]+|\[[0-9a-fA-F:]+\]):(\*|[0-9]+)", v) or re.fullmatch(r"(ipc|inproc)://.+", v)
    if not m:
        return f"expected a ZeroMQ endpoint such as tcp://HOST:PORT, got {v!r}"
    return None if m.group(1) != "tcp" or m.group(3) == "*" else _port(m.group(3), v)


def _port(port: str, whole: str):
    ok = port.isdigit() and 0 <= int(port) <= 65535
    return None if ok else f"port must be 0-65535, got {whole!r}"


RULES = {"positive": _positive, "non_negative": _non_negative, "count": _count, "open_unit": _open_unit,
         "finite": _finite, "size": _size, "host_port": _host_port, "endpoint": _endpoint}


def problem(o: Option, value) -> str | None:
    """What is wrong with `value` for option `o`, or None."""
    return RULES[o.rule](value) if o.rule and value is not None else None


# When a render stops: one of these (the `render` command takes only one).
LIMITS = (
    _opt("time", float, None, f"stop after S seconds of rendering (default {SECONDS:g} if no other limit)",
         rule="positive"),
    _opt("photons", float, None, "stop once N photons are emitted", rule="positive"),
    _opt("iterations", int, None, "stop after K eye iterations", rule="count"),
)
RENDER = (
    _opt("out", str, "out.exr", "output EXR (a PNG preview beside it)"),
    _opt("seed", int, _LIBRARY.seed, "random seed", rule="non_negative"),
    _opt("gather", str, _LIBRARY.gather, "statistics gather", ("grid", "hash")),
    _opt("alpha", float, _LIBRARY.alpha, "radius reduction (eqs. 1-2)", rule="open_unit"),
    _opt("radius", float, _LIBRARY.radius, "initial radius in scene units, the same for every pixel "
         "(default: fitted per pixel to the photons that reach it)", rule="positive"),
    _opt("max_depth", int, None, "scattering events a path may have (default: the scene file's "
         f"integrator's, Mitsuba's max_depth less 1; else {_LIBRARY.max_depth})", rule="count"),
    _opt("direct", str, _LIBRARY.direct, "direct light at hit points: nee (a shadow ray each) or "
         "photons (the paper's pure estimator)", DIRECT_MODES),
    _opt("photons_per_iteration", int, _LIBRARY.photons_per_iteration, "photons between eye iterations "
         "(default: 1.5 per pixel, at least 10,000; osppm with more chunks than fit: grown until "
         "their loads are hidden, within --queue-memory)", rule="count"),
    _opt("photons_per_job", int, None, f"photons per photon job (default {SERVICE_JOB_SIZES['photons_per_job']}, "
         f"{GATHER_AT_TRACERS_PHOTONS_PER_JOB} with --gather-at tracers)", rule="count"),
    _opt("photon_batch", int, _LIBRARY.photon_batch, "deposits per statistics update (server batching)", rule="count"),
    _opt("width", int, None, "image width override", rule="count"),
    _opt("height", int, None, "image height override", rule="count"),
    _opt("threads", int, THREADS, "threads for tracing and the statistics update", rule="count"),
    _opt("exposure", float, 0.0, "PNG preview exposure in stops", rule="finite"),
    _opt("log", str, None, "append JSON-lines progress records here"),
)
# How a scene that is not a chunk store yet is cut into one.
CHUNKING = (
    _opt("budget", str, None, "memory per chunk, BVH included, when subdividing, e.g. 512MiB "
         f"(default {BUDGET_BYTES // 2 ** 20}MiB unless --chunks)", rule="size"),
    _opt("chunks", int, None, "force this many chunks", rule="count"),
    _opt("store_cache", str, default_store_cache(), "where chunk stores made on the fly are kept"),
)
# The paper's optimisations, each of which can be switched off (Figure 15).
OPTIMISATIONS = (
    _opt("cull", bool, _LIBRARY.cull, "cull photons against the hit-point box (§4.3)"),
    _opt("concurrent", bool, True, "trace photons and eye rays at the same time (§3.3); "
         "--no-concurrent alternates them"),
    _opt("client_batching", bool, True, "tracers coalesce packages per chunk (§4.3)"),
)
# The server's running of a render (`render` starts a server too).
SERVICE = (
    _opt("http", str, "127.0.0.1:8080", "status page HOST:PORT, or 'off'", rule="host_port"),
    _opt("min_photon_jobs", int, 1000, "photon jobs kept in flight (the paper's 1k)", rule="count"),
    _opt("snapshot_interval", float, 60.0, "write the image every S seconds", rule="positive"),
    _opt("checkpoint", str, None, "checkpoint directory (default: OUT's name + '.checkpoint')"),
    _opt("checkpoint_interval", float, 60.0, "seconds between checkpoints of the pixel statistics; 0: none",
         rule="non_negative"),
    _opt("resume", str, None, "continue the render saved in this checkpoint directory"),
    _opt("ledger", str, None, "record every statistics update applied in this file, to re-trace and "
         "check later (services/ledger.py)"),
    _opt("gather_at", str, "server", "where photons are gathered: 'server' (the paper's: tracers send every "
         "deposit) or 'tracers' (they keep them and send per-pixel sums by epochs; docs/how-it-works.md)",
         choices=("server", "tracers")),
    _opt("hit_point_stride", int, None, "install the hit points of one eye iteration in N; the others add "
         "only the light their paths saw (default: one set per epoch gathering at the tracers; 1, every "
         "iteration, the paper's, gathering at the server)", rule="count"),
    _opt("batch_growth", int, MOST_MERGED, "gathering at the tracers, one statistics update may merge up to N epochs "
         "while the tracers finish them faster than the server's rounds gather them (1: each epoch its own "
         "batch, the paper's; docs/how-it-works.md)", rule="count"),
    _opt("tracer_timeout", float, 10.0, "drop a tracer silent this long (its jobs are re-emitted); "
         "raise it for chunks that take longer than this to load", rule="positive"),
)
SERVER = LIMITS + RENDER + CHUNKING + OPTIMISATIONS + SERVICE + (
    _opt("bind", str, "tcp://127.0.0.1:5555", "ZeroMQ endpoint tracers connect to", rule="endpoint"),
    _opt("min_tracers", int, 1, "tracers to wait for before rendering", rule="count"),
    _opt("min_tracers_timeout", float, None, "start with the tracers there are (at least one) after "
         "waiting this many seconds for --min-tracers (default: wait for ever)", rule="positive"),
    _opt("drain_timeout", float, 60.0, "at the end, wait this long for jobs in flight", rule="non_negative"),
    _opt("queue_memory", str, None, "deposits held for photon jobs in flight at most this much; past it "
         "no photon job goes out until jobs complete "
         "(default: 1/16 of the machine's memory or its cgroup limit, 32MiB to 1GiB)", rule="size"),
    _opt("curve_secret", str, None, "this server's CURVE key file (dosppm keys): encrypt and authenticate"),
    _opt("curve_clients", str, None, "directory of the public key files of the tracers to admit"),
)
TRACER = (
    _opt("server", str, "tcp://127.0.0.1:5555", "the server's endpoint", rule="endpoint"),
    _opt("bind", str, "tcp://127.0.0.1:*", "endpoint for portal packages from other tracers", rule="endpoint"),
    _opt("advertise", str, None, "address other tracers reach this one at when binding 0.0.0.0; 'auto': "
         "this host's address on the route to the server"),
    _opt("store", str, None, "a local copy of the chunk store (else chunks are fetched)"),
    _opt("cache_dir", str, None, "where fetched chunks are kept"),
    _opt("memory", str, None, "resident chunk memory, e.g. 4GiB (default: the machine's memory or its "
         "cgroup limit, less ~200MiB and the queue; at least one chunk)", rule="size"),
    _opt("queue_memory", str, None, "rays queued here at most this much, when more chunks than fit make "
         "it queue more to hide their loads "
         "(default: 1/16 of the machine's memory or its cgroup limit, 32MiB to 1GiB)", rule="size"),
    _opt("threads", int, THREADS, "tracing threads", rule="count"),
    _opt("id", str, None, "tracer id (default host-pid-random)"),
    _opt("retry", float, 60.0, "keep trying to reach the server this long, in seconds", rule="non_negative"),
    _opt("curve_secret", str, None, "this tracer's CURVE key file (dosppm keys)"),
    _opt("curve_server_key", str, None, "the server's public key file"),
    _opt("curve_clients", str, None, "directory of the public key files of the tracers (its peers)"),
)


def option(name: str, options=SERVER) -> Option:
    return next(o for o in options if o.name == name)


def add_options(parser, options, defaults: bool = True) -> None:
    """A flag per option; with `defaults=False` every flag defaults to None,
    so that `resolve` can tell a flag given from one left out."""
    for o in options:
        flag = "--" + o.name.replace("_", "-")
        default = o.default if defaults else None
        if o.type is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=default, help=o.help)
        else:
            parser.add_argument(flag, type=checked(o.type, o.rule), default=default, choices=o.choices,
                                help=o.help, metavar=flag[2:].replace("-", "_").upper())


def checked(type_, rule: str | None):
    """An argparse `type` that converts and then applies RULES[rule]: a
    bad value is argparse's one-line error naming the flag, exit status 2."""
    def convert(text: str):
        try:
            value = _parse(type_, text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {_NOUN.get(type_, type_.__name__)}, got {text!r}") from None
        why = RULES[rule](value) if rule else None
        if why:
            raise argparse.ArgumentTypeError(why)
        return value
    convert.__name__ = type_.__name__   # argparse names the type in its own messages
    return convert


_NOUN = {int: "an integer", float: "a number", str: "text"}


def _parse(type_, text: str):
    """int, float or str of a flag's text; counts may be written 1_000_000
    or 1e6."""
    if type_ not in (int, float):
        return type_(text)
    text = text.replace("_", "")
    if type_ is float:
        return float(text)
    try:
        return int(text)
    except ValueError:
        f = float(text)
        if not f.is_integer():
            raise
        return int(f)


def add_role_options(parser: argparse.ArgumentParser, options) -> None:
    """The flags of a role (server or tracer): its options, `--config` and `--quiet`."""
    add_options(parser, options, defaults=False)
    parser.add_argument("--config", help="TOML file with these settings")
    parser.add_argument("--quiet", action="store_true")


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
    if o.type is int and isinstance(value, float) and not value.is_integer():
        raise ConfigError(f"{where}: expected an integer, got {value!r}")   # int() would cut it
    try:
        converted = o.type(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected {_NOUN.get(o.type, o.type.__name__)}, got {value!r}") from None
    if o.choices and converted not in o.choices:
        raise ConfigError(f"{where}: expected one of {', '.join(o.choices)}, got {value!r}")
    why = problem(o, converted)
    if why:
        raise ConfigError(f"{where}: {why}")
    return converted


def _read_table(path: str, role: str, known: set) -> dict:
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except OSError as e:
        raise ConfigError(f"{path}: cannot read: {e.strerror}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None
    if role == "tracer" and "worker" in doc:
        raise ConfigError(f"{path}: [worker] is now [tracer]: rename the table")
    table = doc.get(role, {})
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [{role}] must be a table")
    unknown = sorted(set(table) - known)
    if unknown:
        raise ConfigError(f"{path}: [{role}].{unknown[0]}: unknown setting")
    return table


def scene_parameter(text: str) -> tuple[str, str]:
    """`-D NAME=VALUE` (argparse type): a Mitsuba scene file's $NAME."""
    name, eq, value = text.partition("=")
    if not eq or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE (a Mitsuba scene's $NAME), got {text!r}")
    return name, value


def add_scene_parameters(p) -> None:
    p.add_argument("-D", dest="define", action="append", type=scene_parameter, metavar="NAME=VALUE",
                   help="a Mitsuba .xml scene's parameter $NAME, over its <default> (as `mitsuba -D`; "
                        "repeat for more)")


def scene_parameters(args) -> dict | None:
    """The -D NAME=VALUE given, as {name: value}; None when none (a later one wins)."""
    return dict(getattr(args, "define", None) or ()) or None


def render_settings(values: dict, service: bool = False, scene_hints: dict | None = None) -> RenderSettings:
    """RenderSettings from option values (validated): those given (not
    None) replace the defaults of one process, or of the service, and
    those the scene file's integrator fixes (`scene_hints`, its
    `render_settings`: a Mitsuba max_depth)."""
    base = RenderSettings(**service_job_sizes(values.get("gather_at"))) if service else RenderSettings()
    base = dataclasses.replace(base, **scene_settings(scene_hints or {}))
    given = {k: values[k] for k in _SETTINGS_FIELDS if values.get(k) is not None}
    settings = dataclasses.replace(base, **given)
    settings.validate()
    return settings


def chunking(values: dict) -> tuple[int | None, int | None]:
    """(budget_bytes, chunks) to subdivide a scene with: as given, or
    `BUDGET_BYTES` when neither is."""
    budget = parse_bytes(values["budget"], "--budget")
    if budget is None and values["chunks"] is None:
        budget = BUDGET_BYTES
    return budget, values["chunks"]


def stop_limit(seconds: float | None, photons: float | None, iterations: int | None) -> tuple[str, float]:
    """The limit a progress line counts down to, (kind, value): photons,
    else iterations, else seconds (`SECONDS` when no limit is given)."""
    if photons is not None:
        return ("photons", photons)
    if iterations is not None:
        return ("iterations", iterations)
    return ("seconds", seconds if seconds is not None else SECONDS)


_UNITS = {"": 1, "b": 1, "k": 1024, "kib": 1024, "m": 1024 ** 2, "mib": 1024 ** 2,
          "g": 1024 ** 3, "gib": 1024 ** 3}


def parse_bytes(text: str | None, flag: str) -> int | None:
    """'512MiB', '1.5GiB', '64KiB', '1000000' -> bytes (binary units; K, M, G
    are read as KiB, MiB, GiB); None stays None. A bad size is a ValueError
    naming `flag`."""
    if text is None:
        return None
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][0-9]+)?)\s*([A-Za-z]*)\s*", text)
    unit = m.group(2).lower() if m else None
    if not m or unit not in _UNITS:
        raise ValueError(f"{flag}: bad size {text!r}: expected a number with an optional KiB, MiB or GiB suffix")
    value = int(float(m.group(1)) * _UNITS[unit])
    if value <= 0:
        raise ValueError(f"{flag}: bad size {text!r}: must be positive")
    return value


def parse_int(text, flag: str, least: int) -> int:
    """An integer (underscores allowed) of at least `least`; else a
    ValueError naming `flag`."""
    try:
        value = int(str(text).replace("_", ""))
    except ValueError:
        raise ValueError(f"{flag}: expected an integer, got {text!r}") from None
    if value < least:
        raise ValueError(f"{flag}: must be >= {least}, got {value}")
    return value


# argparse types for the flags outside the option table (bench, evaluate,
# subdivide, reference, render's own).
positive_int = checked(int, "count")
positive_float = checked(float, "positive")
non_negative_int = checked(int, "non_negative")
size = checked(str, "size")
