"""The harness's verbs on the `dosppm` command (issue 34): bench,
reference, compare and evaluate are doors into harness/, which the command
loads only when one of them runs (services/cli/harness_verbs.py)."""
from __future__ import annotations

import sys

import numpy as np
import pytest

from dosppm_core.film import write_exr
from harness.cli.main import main as harness_main
from services.cli.main import main as dosppm_main
from tests.helpers.cli import run_python

HARNESS_VERBS = ("bench", "reference", "compare", "evaluate")


def test_building_the_command_loads_no_harness_module():
    """What `dosppm render`, `server` and `worker` do before they run."""
    code = ("import sys; from services.cli.main import build_parser; build_parser(); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'harness'))")
    said = run_python("-c", code, timeout=120)
    assert said.returncode == 0, said.stderr
    assert said.stdout.strip() == "[]"


@pytest.mark.parametrize("verb", HARNESS_VERBS)
def test_each_verb_answers_its_help_from_the_harness(verb, capsys):
    with pytest.raises(SystemExit) as e:
        dosppm_main([verb, "--help"])
    assert e.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: dosppm {verb} ")


def test_the_door_passes_every_word_through(tmp_path, capsys):
    """`dosppm compare` and `python -m harness compare` are one command."""
    a, b = str(tmp_path / "a.exr"), str(tmp_path / "b.exr")
    write_exr(a, np.full((2, 3, 3), 2.0, np.float32))
    write_exr(b, np.full((2, 3, 3), 1.0, np.float32))
    assert dosppm_main(["compare", a, b, "--json"]) == 0
    via_door = capsys.readouterr().out
    assert harness_main(["compare", a, b, "--json"]) == 0
    assert via_door == capsys.readouterr().out and '"rmse": 1.0' in via_door


def test_without_the_harness_a_verb_is_one_line_and_render_is_untouched(monkeypatch, capsys):
    """An install without harness/ (the Docker image copies only the
    product): its verbs say so in one line, exit 1."""
    monkeypatch.setitem(sys.modules, "harness.cli.main", None)    # makes the import fail
    assert dosppm_main(["bench", "--photons", "1000"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bench: the evaluation harness (harness/) is not installed" in err
