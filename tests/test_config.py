"""Settings of the server and tracer roles (`dosppm server`, `dosppm
worker`): flag > environment > TOML file > default, clear errors naming the
file, table and key, and one default per render setting."""
from __future__ import annotations

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
    with pytest.raises(config.ConfigError, match=r"\[server\]\.min_tracers: expected int"):
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
    assert (service.photons_per_job, service.tile_pixels) == (1024, 4096)
    for name in ("seed", "alpha", "radius", "max_depth", "gather", "photons_per_iteration", "photon_batch",
                 "cull"):
        assert getattr(service, name) == getattr(library, name), name
    args = _args(["render", "--mode", "sppm"])
    assert args.photons_per_job is None
    here = config.render_settings(vars(args))
    assert (here.photons_per_job, here.tile_pixels) == (library.photons_per_job, library.tile_pixels)
    assert config.render_settings(vars(_args(["render", "--photons-per-job", "64"]))).photons_per_job == 64
