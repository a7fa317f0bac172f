"""The performance tables are generated from benchmarks/results/, never
typed (issue 13): a marked table is replaced from its results file, names
the file, commit and command, and the committed docs are in step with the
committed results."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess

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