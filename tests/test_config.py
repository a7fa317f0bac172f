"""Settings of the server and worker roles: flag > environment > TOML file
> default, and clear errors naming the file, table and key."""
from __future__ import annotations

import pytest

from services.cli import main as cli
from services import config


def _args(argv):
    return cli.build_parser().parse_args(argv)


def test_precedence_flag_env_file_default(tmp_path):
    f = tmp_path / "w.toml"
    f.write_text('[worker]\nserver = "tcp://file:1"\nthreads = 3\nbind = "tcp://0.0.0.0:5600"\n')
    args = _args(["worker", "--config", str(f), "--threads", "7"])
    v = config.resolve(args, "worker", config.WORKER, environ={"DOSPPM_THREADS": "5",
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
