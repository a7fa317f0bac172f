"""The freshness check of the quoted tables (issue 34): a results file is
stale once a later commit changed the product's code or the benchmark
script its recorded command ran, or when it names no clean commit.
Checked on a throwaway git repository, so that it can fail both ways."""
from __future__ import annotations

import json
import re
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


def test_comments_and_docstrings_do_not_age_it_but_code_in_the_same_file_does(repo):
    """A review that rewords a kernel's docstrings changes no figure; a
    changed constant beside a new comment does."""
    root, code = repo
    _write(root, "dosppm_core/kernel.py", '"""A kernel."""\n\ndef f(a):\n    return a + 1\n')
    code = _commit(root, "kernel")
    _measured(root, code)
    _commit(root, "results")
    _write(root, "dosppm_core/kernel.py",
           '"""A kernel, reworded."""\n\n\ndef f(a):  # why\n    """Adds one."""\n    return a + 1\n')
    _commit(root, "reworded")
    assert tables.staleness("replay", str(root)) is None
    _write(root, "dosppm_core/kernel.py", '"""A kernel."""\n\ndef f(a):  # why\n    return a + 2\n')
    later = _commit(root, "code")
    why = tables.staleness("replay", str(root))
    assert why is not None and later[:10] in why and "dosppm_core/kernel.py" in why


def _measured_with(root, code, table) -> None:
    """The replay's results file and `table`'s, both measured at `code`."""
    for rel in (RESULTS, tables.TABLES[table][0]):
        _write(root, rel, json.dumps({"provenance": {"commit": code, "command": "x"}}))
    _commit(root, "results")


def test_a_library_table_is_not_aged_by_the_services(repo):
    """sppm-phases times the library in one process: a server change leaves
    it fresh, a library change does not; replay measures both."""
    root, code = repo
    _measured_with(root, code, "sppm-phases")
    _write(root, "services/server/state.py", "y = 1\n")
    _commit(root, "server")
    assert tables.staleness("sppm-phases", str(root)) is None
    assert tables.staleness("replay", str(root)) is not None
    _write(root, "dosppm_core/kernel.py", "x = 3\n")
    _commit(root, "library")
    assert tables.staleness("sppm-phases", str(root)) is not None


def test_a_peer_driver_ages_only_the_tables_that_run_the_peers(repo):
    """harness/pbrt.py writes pbrt-v4's scenes: the Sponza evaluation
    measures it, the replay does not."""
    root, code = repo
    _measured_with(root, code, "accuracy-sponza-80s")
    _write(root, "harness/pbrt.py", "depth = 100\n")
    _commit(root, "pbrt")
    assert tables.staleness("replay", str(root)) is None
    assert "harness/pbrt.py" in tables.staleness("accuracy-sponza-80s", str(root))


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


def test_run_all_regenerates_every_quoted_file():
    """Every results file a document quotes is written by a step of
    run_all: named there or in a script it steps, or the default output
    of a benchmark it runs (tables.py, which names them all, aside)."""
    with open(os.path.join(REPO, "benchmarks", "run_all"), encoding="utf-8") as f:
        text = f.read()
    corpus = [text]
    for word in re.findall(r"^\s*step (?:python )?(?:-m )?(\S+)", text, re.M):
        script = word if word.endswith((".py", ".sh")) else word.replace(".", "/") + ".py"
        if script != "benchmarks/tables.py" and os.path.exists(os.path.join(REPO, script)):
            with open(os.path.join(REPO, script), encoding="utf-8") as f:
                corpus.append(f.read())
    corpus = "\n".join(corpus)
    missing = []
    for name in tables.quoted(root=REPO):
        path = tables.TABLES[name][0]
        target = os.path.dirname(path) if path.endswith("/results.json") else path
        if target not in corpus and not (target.endswith(".json") and os.path.basename(target) in corpus):
            missing.append(f"{name}: {path}")
    assert not missing, "quoted but not regenerated by benchmarks/run_all: " + "; ".join(missing)
