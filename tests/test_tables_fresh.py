"""The freshness check of the quoted tables (issue 34): a results file is
stale once a later commit changed the product's code or the benchmark
script its recorded command ran, or when it names no clean commit.
Checked on a throwaway git repository, so that it can fail both ways."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from tests.helpers.paths import REPO

sys.path.insert(0, os.path.join(REPO, "benchmarks"))
import tables  # noqa: E402

RESULTS = tables.TABLES["replay"][0]


def _git(root, *args) -> str:
    env = dict(os.environ, GIT_AUTHOR_NAME="t", GIT_AUTHOR_EMAIL="t@t", GIT_COMMITTER_NAME="t",
               GIT_COMMITTER_EMAIL="t@t")
    return subprocess.run(["git", "-C", str(root), *args], check=True, capture_output=True, text=True,
                          env=env).stdout.strip()


def _write(root, rel, text):
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def _commit(root, msg) -> str:
    _git(root, "add", "-A")
    _git(root, "commit", "-qm", msg)
    return _git(root, "rev-parse", "HEAD")


def _measured(root, commit, command="benchmarks/bench_x.py --seconds 1"):
    _write(root, RESULTS, json.dumps({"provenance": {"commit": commit, "command": command}}))


@pytest.fixture
def repo(tmp_path):
    _git(tmp_path, "init", "-q")
    _write(tmp_path, "dosppm_core/kernel.py", "x = 1\n")
    _write(tmp_path, "benchmarks/bench_x.py", "print(1)\n")
    _write(tmp_path, "README.md", "hello\n")
    return tmp_path, _commit(tmp_path, "code")


def test_a_file_measured_on_the_last_code_is_fresh_and_docs_do_not_age_it(repo):
    root, code = repo
    _measured(root, code)
    _commit(root, "results")
    _write(root, "README.md", "the table\n")
    _commit(root, "docs")
    assert tables.staleness("replay", str(root)) is None


@pytest.mark.parametrize("changed", ["dosppm_core/kernel.py", "harness/replay.py", "benchmarks/bench_x.py"])
def test_a_later_change_to_the_code_or_its_script_makes_it_stale(repo, changed):
    root, code = repo
    _measured(root, code)
    _commit(root, "results")
    _write(root, changed, "x = 2\n")
    later = _commit(root, "change")
    why = tables.staleness("replay", str(root))
    assert why is not None and later[:10] in why and code[:10] in why


def test_a_dirty_or_unknown_commit_or_none_is_stale(repo):
    root, code = repo
    for commit, words in ((code + "+dirty", "not a clean commit"), ("0" * 40, "not a clean commit")):
        _measured(root, commit)
        assert words in tables.staleness("replay", str(root))
    _write(root, RESULTS, json.dumps({"figures": 1}))
    assert "no provenance" in tables.staleness("replay", str(root))


def test_run_all_ends_by_checking_freshness():
    with open(os.path.join(REPO, "benchmarks", "run_all"), encoding="utf-8") as f:
        steps = [ln for ln in f.read().splitlines() if ln.startswith("step ")]
    assert steps[-1].startswith("step python benchmarks/tables.py --fresh")
