"""Settings of the server and tracer roles (`dosppm server`, `dosppm
worker`): flag > environment > TOML file > default, clear errors naming the
file, table and key, and one default per render setting."""
from __future__ import annotations

import re

import pytest

from dosppm_core.settings import RenderSettings
from services import config
from services.cli import main as cli


def _args(argv):
    return cli.build_parser().parse_args(argv)


def test_precedence_flag_env_file_default(tmp_path):
    f = tmp_path / "t.toml"
    f.write_text('[tracer]\nserver = "tcp://file:1"\nthreads = 3\nbind = "tcp://0.0.0.0:5600"\n')
    args = _args(["worker", "--config", str(f), "--threads", "7"])
    v = config.resolve(args, "tracer", config.TRACER, environ={"DOSPPM_THREADS": "5",
                                                              "DOSPPM_SERVER": "tcp://env:2"})
    assert v["threads"] == 7                        # flag beats environment and file
    assert v["server"] == "tcp://env:2"             # environment beats file
    assert v["bind"] == "tcp://0.0.0.0:5600"        # file beats default
    assert v["advertise"] is None                   # default


def test_unknown_key_in_file_names_file_table_and_key(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text('[server]\nbindd = "x"\n')
    with pytest.raises(config.ConfigError, match=r"s\.toml: \[server\]\.bindd: unknown setting"):
        config.resolve(_args(["server", "--config", str(f)]), "server", config.SERVER, environ={})


def test_bad_values_are_one_line_errors(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text('[server]\nmin_tracers = "two"\n')
    with pytest.raises(config.ConfigError, match=r"\[server\]\.min_tracers: expected an integer, got .two."):
        config.resolve(_args(["server", "--config", str(f)]), "server", config.SERVER, environ={})
    with pytest.raises(config.ConfigError, match="DOSPPM_CULL: expected true or false"):
        config.resolve(_args(["server"]), "server", config.SERVER, environ={"DOSPPM_CULL": "maybe"})
    f.write_text("[server\n")
    with pytest.raises(config.ConfigError, match="not valid TOML"):
        config.resolve(_args(["server", "--config", str(f)]), "server", config.SERVER, environ={})


def test_switches_read_from_flags_and_environment():
    v = config.resolve(_args(["server", "--no-cull"]), "server", config.SERVER,
                       environ={"DOSPPM_CONCURRENT": "false"})
    assert v["cull"] is False and v["concurrent"] is False and v["client_batching"] is True


def test_cli_exits_nonzero_with_one_line_for_a_bad_file(tmp_path, capsys):
    assert cli.main(["worker", "--config", str(tmp_path / "missing.toml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing.toml" in err[0]


def test_old_worker_table_is_an_error_naming_the_new_one(tmp_path):
    f = tmp_path / "t.toml"
    f.write_text('[worker]\nserver = "tcp://file:1"\n')
    with pytest.raises(config.ConfigError, match=r"t\.toml: \[worker\] is now \[tracer\]"):
        config.resolve(_args(["worker", "--config", str(f)]), "tracer", config.TRACER, environ={})


def test_render_defaults_are_the_library_s_but_the_service_s_job_sizes():
    """The flags and the file take their defaults from RenderSettings; only
    the job sizes differ, and only in the service."""
    library = RenderSettings()
    v = config.resolve(_args(["server"]), "server", config.SERVER, environ={})
    service = config.render_settings(v, service=True)
    assert (service.photons_per_job, service.tile_pixels) == (4096, 4096)
    for name in ("seed", "alpha", "radius", "max_depth", "gather", "photons_per_iteration", "photon_batch",
                 "cull"):
        assert getattr(service, name) == getattr(library, name), name
    args = _args(["render", "--mode", "sppm"])
    assert args.photons_per_job is None
    here = config.render_settings(vars(args))
    assert (here.photons_per_job, here.tile_pixels) == (library.photons_per_job, library.tile_pixels)
    assert config.render_settings(vars(_args(["render", "--photons-per-job", "64"]))).photons_per_job == 64
    # Gathering at the tracers, a job costs the server only its accounting: larger by default.
    v = config.resolve(_args(["server", "--gather-at", "tracers"]), "server", config.SERVER, environ={})
    assert config.render_settings(v, service=True).photons_per_job == 16384
    v = config.resolve(_args(["server", "--gather-at", "tracers", "--photons-per-job", "2048"]), "server",
                       config.SERVER, environ={})
    assert config.render_settings(v, service=True).photons_per_job == 2048


# -- every numeric or address setting is checked, wherever it comes from --------

BAD_FLAGS = [
    (["render", "--time", "-5"], "--time", "must be > 0, got -5"),
    (["render", "--time", "nan"], "--time", "must be > 0, got nan"),
    (["render", "--photons", "0"], "--photons", "must be > 0"),
    (["render", "--iterations", "0"], "--iterations", "must be >= 1, got 0"),
    (["render", "--photons-per-iteration", "1.5e5x"], "--photons-per-iteration", "expected an integer"),
    (["render", "--photon-batch", "-1"], "--photon-batch", "must be >= 1"),
    (["render", "--alpha", "1"], "--alpha", "must lie in (0, 1)"),
    (["render", "--radius", "0"], "--radius", "must be > 0"),
    (["render", "--width", "0"], "--width", "must be >= 1"),
    (["render", "--threads", "0"], "--threads", "must be >= 1"),
    (["render", "--tracers", "0"], "--tracers", "must be >= 1"),
    (["render", "--budget", "12XB"], "--budget", "bad size '12XB'"),
    (["render", "--memory", "0"], "--memory", "bad size '0': must be positive"),
    (["render", "--http", "localhost:70000"], "--http", "port must be 0-65535"),
    (["render", "--tracer-timeout", "0"], "--tracer-timeout", "must be > 0"),
    (["render", "--checkpoint-interval", "-1"], "--checkpoint-interval", "must be >= 0"),
    (["server", "--bind", "tcp://0.0.0.0:99999"], "--bind", "port must be 0-65535"),
    (["server", "--min-tracers", "0"], "--min-tracers", "must be >= 1"),
    (["worker", "--server", "10.0.0.1:5555"], "--server", "expected a ZeroMQ endpoint"),
    (["worker", "--retry", "-1"], "--retry", "must be >= 0"),
    (["bench", "--repeats", "0"], "--repeats", "must be >= 1"),
    (["evaluate", "mini", "--budget-s", "0"], "--budget-s", "must be > 0"),
    (["subdivide", "cornell-box", "--out", "x", "--chunks", "0"], "--chunks", "must be >= 1"),
]


@pytest.mark.parametrize("argv,flag,why", BAD_FLAGS, ids=[" ".join(a) for a, _, _ in BAD_FLAGS])
def test_a_bad_flag_is_one_line_naming_it_and_exit_2(argv, flag, why, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert err.count("\n") == 1 and f"argument {flag}: {why}" in err, err


def test_counts_read_as_a_user_writes_them():
    args = _args(["render", "--photons-per-iteration", "1e6", "--photon-batch", "2_000_000", "--time", "1.5"])
    assert (args.photons_per_iteration, args.photon_batch, args.time) == (1_000_000, 2_000_000, 1.5)


@pytest.mark.parametrize("name,value,why", [
    ("DOSPPM_MIN_TRACERS", "0", "environment DOSPPM_MIN_TRACERS: must be >= 1, got 0"),
    ("DOSPPM_TIME", "-5", "environment DOSPPM_TIME: must be > 0, got -5"),
    ("DOSPPM_BIND", "tcp://*:port", "environment DOSPPM_BIND: expected a ZeroMQ endpoint"),
    ("DOSPPM_HTTP", "8080", "environment DOSPPM_HTTP: expected HOST:PORT or 'off'"),
])
def test_a_bad_environment_value_is_an_error_naming_it(name, value, why):
    with pytest.raises(config.ConfigError, match=re.escape(why)):
        config.resolve(_args(["server"]), "server", config.SERVER, environ={name: value})


@pytest.mark.parametrize("key,value,why", [
    ("threads", "0", "[tracer].threads: must be >= 1, got 0"),
    ("threads", "2.5", "[tracer].threads: expected an integer, got 2.5"),
    ("memory", '"lots"', "[tracer].memory: bad size 'lots'"),
    ("retry", "-3.0", "[tracer].retry: must be >= 0, got -3"),
])
def test_a_bad_file_value_is_an_error_naming_file_and_key(tmp_path, key, value, why):
    f = tmp_path / "t.toml"
    f.write_text(f"[tracer]\n{key} = {value}\n")
    with pytest.raises(config.ConfigError, match=re.escape(f"{f}: {why}")):
        config.resolve(_args(["worker", "--config", str(f)]), "tracer", config.TRACER, environ={})


def test_a_bad_environment_value_exits_2_with_one_line(capsys, monkeypatch):
    monkeypatch.setenv("DOSPPM_THREADS", "-2")
    assert cli.main(["worker"]) == 2
    assert capsys.readouterr().err == "dosppm: error: environment DOSPPM_THREADS: must be >= 1, got -2\n"
