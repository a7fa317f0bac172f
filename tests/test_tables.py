"""The performance tables are generated from benchmarks/results/, never
typed (issue 13): a marked table is replaced from its results file, names
the file, commit and command, and the committed docs are in step with the
committed results."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys

import pytest

from harness import provenance
from tests.helpers.paths import REPO as ROOT


def _tables():
    spec = importlib.util.spec_from_file_location("tables", os.path.join(ROOT, "benchmarks", "tables.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _core_results(root, ratio):
    result = {"scene": "cornell-glass", "triangles": 110606, "raw_embree_rays_per_s": 5.6e6,
              "photon_rays_per_s": 5.6e6 * ratio, "ratio_to_raw": ratio}
    path = os.path.join(root, "benchmarks", "results")
    os.makedirs(path)
    argv = ["benchmarks/core.sh", "--repeats", "5"]
    with open(os.path.join(path, "core.json"), "w") as f:
        json.dump({"provenance": provenance.provenance(argv), "results": [result]}, f)


def test_a_marked_table_is_replaced_from_its_results_file(tmp_path):
    tables = _tables()
    _core_results(str(tmp_path), 0.61)
    text = "before\n<!-- table:core -->\nstale | 0.55\n<!-- /table:core -->\nafter\n"
    out = tables.fill(text, root=str(tmp_path))
    assert out.startswith("before\n<!-- table:core -->\n") and out.endswith("<!-- /table:core -->\nafter\n")
    assert "0.55" not in out and "| ratio to raw (target >= 0.5) | 0.61 |" in out
    head = provenance.commit()[:10]
    assert f"Source: [benchmarks/results/core.json](benchmarks/results/core.json), commit {head}" in out
    assert "`benchmarks/core.sh --repeats 5`" in out
    assert tables.fill(out, root=str(tmp_path)) == out      # a second run changes nothing


def test_an_unknown_table_name_is_an_error(tmp_path):
    with pytest.raises(KeyError, match="unknown table 'cored'"):
        _tables().fill("<!-- table:cored -->\n<!-- /table:cored -->\n", root=str(tmp_path))


def test_the_committed_docs_match_the_committed_results():
    assert _tables().main(["--check"]) == 0


def test_provenance_names_commit_machine_and_command():
    p = provenance.provenance(["benchmarks/osppm.py", "--chunks", "1 8"])
    assert len(p["commit"].split("+")[0]) == 40
    assert p["machine"]["cpu_count"] == os.cpu_count() and p["machine"]["numba"]
    assert p["command"] == "benchmarks/osppm.py --chunks '1 8'"
    assert p["date"].endswith("+00:00")


def test_every_sample_is_kept_beside_the_median():
    runs = [{"photons_per_s": v, "scene": "s"} for v in (3.0, 1.0, 2.0)]
    out = provenance.median_of(runs)
    assert out["photons_per_s"] == 2.0 and out["repeats"] == 3
    assert [s["photons_per_s"] for s in out["samples"]] == [3.0, 1.0, 2.0]


def test_dosppm_bench_writes_every_timing_and_its_provenance(tmp_path):
    """`dosppm bench --json` (what benchmarks/core.sh runs) keeps every
    timing of every figure, not only the medians it reports."""
    from harness import bench
    from tests.helpers.scenes import small_scene
    result = bench.bench_scene(small_scene("cornell-box", 32), photons=20_000, repeats=3,
                               paper_hit_points=4096)
    path = str(tmp_path / "core.json")
    bench.write_json(path, [result])
    with open(path) as f:
        doc = json.load(f)
    assert doc["provenance"]["commit"] == provenance.commit()
    got = doc["results"][0]
    assert set(got["samples_s"]) >= {"photon_pass", "raw_embree", "eye_pass", "update_ms_per_1M_grid_sorted",
                                     "update_paper_hit_points"}
    assert got["hit_points"] < 1024 and 3000 < got["hit_points_paper"] < 5200
    for name, times in got["samples_s"].items():
        assert len(times) == 3 and all(t > 0 for t in times), name
    passes = sorted(got["samples_s"]["photon_pass"])
    assert got["photon_paths_per_s"] == pytest.approx(20_000 / passes[1])


def test_provenance_looks_for_changes_in_the_whole_repository(tmp_path, monkeypatch):
    """A figure measured with any change in the tree is dirty: an edit in
    dosppm_core/, services/ or benchmarks/, staged or not, or a new file
    git does not ignore; not one in benchmarks/results/ (issue 34: ROOT was
    services/, so edits elsewhere left a figure labelled clean)."""
    assert os.path.exists(os.path.join(provenance.ROOT, "pyproject.toml"))
    for name in ("dosppm_core/k.py", "services/s.py", "benchmarks/b.py", "benchmarks/results/r.json"):
        os.makedirs(tmp_path / os.path.dirname(name), exist_ok=True)
        (tmp_path / name).write_text("x = 1\n")
    (tmp_path / ".gitignore").write_text("*.exr\n")

    def git(*args):
        subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=tmp_path, check=True,
                       capture_output=True)
    git("init", "-q")
    git("add", ".")
    git("commit", "-q", "-m", "c")
    monkeypatch.setattr(provenance, "ROOT", str(tmp_path))

    def dirty_after(change) -> bool:
        change()
        out = provenance.commit().endswith("+dirty")
        git("reset", "-q", "--hard")
        git("clean", "-q", "-fd")
        return out
    assert not dirty_after(lambda: None)
    assert not dirty_after(lambda: (tmp_path / "benchmarks/results/r.json").write_text("x = 2\n"))
    assert not dirty_after(lambda: (tmp_path / "benchmarks/results/new.json").write_text("{}\n"))
    assert not dirty_after(lambda: (tmp_path / "out.exr").write_text("ignored\n"))
    for name in ("dosppm_core/k.py", "services/s.py", "benchmarks/b.py"):
        assert dirty_after(lambda: (tmp_path / name).write_text("x = 2\n")), name
    assert dirty_after(lambda: (tmp_path / "dosppm_core/new.py").write_text("x = 3\n")), "an untracked module"

    def staged():
        (tmp_path / "benchmarks/b.py").write_text("x = 2\n")
        git("add", "benchmarks/b.py")
    assert dirty_after(staged)

# The reliability tables (issue 34): k of n runs, failures counted, thin
# figures and mixed commits said, the timeout shown.

CLEAN, OTHER = "a" * 40, "b" * 40 + "+dirty"


def _reliability_doc() -> dict:
    return {
        "provenance": provenance.provenance(["benchmarks/reliability.sh"]) | {"commit": CLEAN},
        "tests": {
            # Five runs, two evicted; one failed before the eviction was timed.
            "tracer killed (SIGKILL)": {"evicted": [1, 0, 1, 0, 0], "timeout_s": [3.0] * 5,
                                        "detected_s": [0.5, 1.2, 0.7, 0.6]},
            # Three runs, all rejoined: fewer than five.
            "cable cut 8 s, then back": {"rejoined": [1, 1, 1], "timeout_s": [3, 3, 3]},
            # Recorded before the flag existed.
            "16 tracers, 1k jobs in flight, one stopped 8 s": {"server_peak_rss_mib": [469]},
        },
        "runs": {"tracer killed (SIGKILL)": {"commit": CLEAN, "date": "2026-11-28T10:00:00+00:00"},
                 "cable cut 8 s, then back": {"commit": CLEAN, "date": "2026-11-28T10:00:00+00:00"},
                 "16 tracers, 1k jobs in flight, one stopped 8 s": {"commit": OTHER, "date": "2026-11-25"}},
    }


def _reliability_rows(text: str) -> dict:
    return {line.split(" | ")[0].strip("| "): line for line in text.splitlines() if line.startswith("| ")}


def test_the_reliability_table_says_k_of_n_with_failures_and_thin_rows():
    tables = _tables()
    rows = _reliability_rows(tables._reliability(_reliability_doc()))
    killed = rows["tracer killed (SIGKILL)"]
    assert "evicted in 2 of 5 runs |" in killed and "fewer than" not in killed
    # The median (range) over the four runs that timed it, and that only four did.
    assert "detected s 0.65 (0.5-1.2) [4 of 5 runs measured]" in killed
    assert "| 3 s |" in killed and f"| {CLEAN[:10]}, 2026-11-28 |" in killed
    assert "rejoined in 3 of 3 runs (n=3, fewer than 5)" in rows["cable cut 8 s, then back"]
    load = rows["16 tracers, 1k jobs in flight, one stopped 8 s"]
    assert "success not recorded in 1 run (n=1, fewer than 5)" in load and "| not recorded |" in load
    assert f"{OTHER[:10]}+dirty" in load


def test_the_readme_reliability_table_says_k_of_n_and_the_timeout():
    rows = _reliability_rows(_tables()._reliability_short(_reliability_doc()))
    assert rows["tracer SIGKILL"] == "| tracer SIGKILL | 3 s | 2 of 5 | evicted after 0.65 (0.5-1.2) s |"
    assert rows["cable cut 8 s, then back"] == "| cable cut 8 s, then back | 3 s | 3 of 3 (< 5 runs) | - |"
    assert rows["16 tracers, one stopped 8 s"].startswith("| 16 tracers, one stopped 8 s | ? | ? of 1 (< 5 runs) |")


def test_the_reliability_source_line_names_the_runs_commits(tmp_path):
    tables = _tables()
    os.makedirs(tmp_path / "benchmarks" / "results")
    doc = _reliability_doc()
    path = tmp_path / "benchmarks" / "results" / "reliability.json"
    path.write_text(json.dumps(doc))
    full = tables.render("reliability", root=str(tmp_path))
    assert f"rows from different commits: {CLEAN[:10]} (2 rows), {OTHER[:10]}+dirty (1 row)" in full
    assert "mixed commits: " + f"{CLEAN[:7]} (2 rows), {OTHER[:7]}+dirty (1 row)" in \
        tables.render("reliability-short", root=str(tmp_path))
    # One commit: named as it is, +dirty kept (the file's top commit is not it).
    for test in doc["runs"]:
        doc["runs"][test]["commit"] = OTHER
    path.write_text(json.dumps(doc | {"dirty_allowed": True}))
    one = tables.render("reliability", root=str(tmp_path))
    assert f"commit {OTHER[:10]}+dirty (run with --dirty), " in one and CLEAN[:10] not in one


def test_a_fault_test_records_a_failed_run_as_a_zero(monkeypatch):
    from tests.helpers import figures
    monkeypatch.setattr(figures, "_FIGURES", {})
    with figures.outcome("t", "evicted", timeout_s=3) as fig:
        fig["detected_s"] = 0.5
    with pytest.raises(AssertionError):
        with figures.outcome("t", "evicted", timeout_s=3) as fig:
            assert False, "not evicted"
    with pytest.raises(RuntimeError):
        with figures.outcome("t", "evicted", timeout_s=3) as fig:
            fig["detected_s"] = 9.0
            raise RuntimeError("an error after measuring")
    with pytest.raises(pytest.skip.Exception):
        with figures.outcome("t", "evicted", timeout_s=3):
            pytest.skip("no netns")                   # a skip is no run
    assert figures._FIGURES == {"t": {"evicted": [1, 0, 0], "timeout_s": [3, 3, 3], "detected_s": [0.5, 9.0]}}


def test_failed_pytest_runs_add_zeros_to_the_results_file(tmp_path):
    """Three pytest runs of a test that passes, fails before measuring,
    then passes, through the conftest hook the repository's tests use: the
    file holds [1, 0, 1], and both measurements."""
    (tmp_path / "conftest.py").write_text(
        "from tests.helpers import figures\n\n\ndef pytest_terminal_summary():\n    figures.write_if_asked()\n")
    (tmp_path / "test_fault.py").write_text(
        "import os\nfrom tests.helpers import figures\n\n\ndef test_fault():\n"
        "    with figures.outcome('a fault', 'resumed', timeout_s=3) as fig:\n"
        "        assert os.environ['PASS'] == '1'\n"
        "        fig['photons'] = 7\n")
    out = tmp_path / "reliability.json"
    for passes in ("1", "0", "1"):
        env = dict(os.environ, PYTHONPATH=ROOT, PASS=passes, DOSPPM_RECORD_FIGURES=str(out))
        r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(tmp_path)],
                           cwd=tmp_path, env=env, capture_output=True, text=True)
        assert r.returncode == (0 if passes == "1" else 1), r.stdout + r.stderr
    doc = json.loads(out.read_text())
    assert doc["tests"]["a fault"] == {"resumed": [1, 0, 1], "timeout_s": [3, 3, 3], "photons": [7, 7]}
    assert doc["runs"]["a fault"]["commit"] == provenance.commit()
