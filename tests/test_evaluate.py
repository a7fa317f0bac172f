"""`dosppm evaluate`, the CI-sized suite: on any machine, error falls as
render time grows (consistency) and no pixel is ever NaN or Inf; the
outputs are complete and a peer that is not installed is skipped."""
import json
import math
import os

import numpy as np
import pytest

from harness import evaluate, suites
from services.cli.main import main

pytestmark = pytest.mark.reference   # the references are Mitsuba's


@pytest.fixture(scope="module")
def mini(tmp_path_factory):
    out = tmp_path_factory.mktemp("evaluation")
    cache = os.environ.get("DOSPPM_TEST_REFERENCE_CACHE") or str(out / "references")
    ev = evaluate.evaluate(evaluate.SUITES["mini"], 4.0, cache_dir=cache, log=lambda _l: None)
    evaluate.write_results(ev, str(out))
    return ev, out


def _curve(ev, scene, method):
    return sorted((s.seconds, s) for s in ev.samples if s.scene == scene and s.method == method)


@pytest.mark.slow   # `mini` renders every method of the suite: about a minute
def test_every_method_stops_at_every_budget_with_finite_pixels(mini):
    ev, _ = mini
    assert not ev.failed and not ev.skipped
    for case in evaluate.SUITES["mini"].cases:
        for method in evaluate.SUITES["mini"].methods:
            curve = _curve(ev, case.scene, method)
            assert len(curve) >= 2, f"{case.scene}/{method}: {len(curve)} stops"
            assert all(s.finite for _, s in curve), f"{case.scene}/{method}: NaN or Inf pixels"
            assert all(math.isfinite(s.relmse) for _, s in curve)


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["cornell-box", "cardioid"])
@pytest.mark.parametrize("method", ["sppm-grid", "osppm-c4"])
def test_error_falls_as_render_time_grows(mini, scene, method):
    """Consistency: the longest render is better than the shortest by a
    margin noise cannot close (the time ratio is 8)."""
    ev, _ = mini
    curve = _curve(ev, scene, method)
    first, last = curve[0][1], curve[-1][1]
    assert last.seconds >= 4 * first.seconds
    assert last.relmse < 0.8 * first.relmse, [(round(t, 2), s.relmse) for t, s in curve]
    assert last.blurred_relmse < first.blurred_relmse


@pytest.mark.slow
def test_sppm_renders_the_point_light_caustic_that_path_tracing_cannot(mini):
    """On the cardioid, a path tracer misses the caustic altogether: the
    error of its blurred image (noise averaged away, bias left) stops
    falling once noise is gone, and stays above SPPM's, which keeps falling."""
    ev, _ = mini
    path = [s for _, s in _curve(ev, "cardioid", "mitsuba-path") if s.seconds >= 0.1]
    sppm = [s for _, s in _curve(ev, "cardioid", "sppm-grid")]
    assert path[-1].blurred_relmse > 0.9 * path[0].blurred_relmse
    assert path[-1].bias < -0.02                      # darker: the caustic is missing
    assert sppm[-1].blurred_relmse < sppm[0].blurred_relmse
    assert sppm[-1].blurred_relmse < 0.7 * path[-1].blurred_relmse


@pytest.mark.slow
def test_outputs_name_every_sample_and_the_claims(mini):
    ev, out = mini
    doc = json.loads((out / "results.json").read_text())
    assert len(doc["samples"]) == len(ev.samples)
    assert doc["references"].keys() == {"cornell-box", "cardioid"}
    rows = (out / "results.csv").read_text().splitlines()
    assert len(rows) == len(ev.samples) + 1
    summary = (out / "summary.md").read_text()
    assert "cardioid (caustic): Mitsuba path relMSE / SPPM grid relMSE" in summary


def test_the_blended_reference_uses_path_exactly_where_the_camera_sees_the_mirror():
    scene = evaluate.suite_scene(evaluate.SUITES["mini"], evaluate.SUITES["mini"].cases[1])
    share = evaluate.specular_first_hit_share(scene, rays_per_pixel=8)
    assert share.shape == (32, 32)
    assert 0.02 < share.mean() < 0.5          # the ring covers part of the view
    assert share.max() == 1.0 and share.min() == 0.0


def test_a_missing_peer_is_skipped_not_failed(monkeypatch, tmp_path):
    monkeypatch.setattr(evaluate, "method_available",
                        lambda m: "not installed" if m.kind == "mitsuba" else None)
    monkeypatch.setattr(evaluate, "reference_image",
                        lambda scene, case, spp, cache: (np.ones((32, 32, 3), np.float32), None))
    ev = evaluate.evaluate(evaluate.SUITES["mini"], 0.5, methods=["sppm-grid", "mitsuba-path"],
                           scenes=["cornell-box"], log=lambda _l: None)
    assert ev.skipped == {"mitsuba-path": "not installed"} and not ev.failed
    assert {s.method for s in ev.samples} == {"sppm-grid"}


def test_cli_rejects_a_scene_outside_the_suite(capsys):
    assert main(["evaluate", "mini", "--scene", "thin-wall"]) == 2
    err = capsys.readouterr().err
    assert "'thin-wall' is not in suite 'mini'" in err and len(err.strip().splitlines()) == 1


def test_re_running_one_scene_keeps_the_others_results(monkeypatch, tmp_path):
    monkeypatch.setattr(evaluate, "reference_image",
                        lambda scene, case, spp, cache: (np.ones((32, 32, 3), np.float32), None))
    run = dict(methods=["sppm-grid"], log=lambda _l: None, out_dir=str(tmp_path))
    evaluate.evaluate(evaluate.SUITES["mini"], 0.3, scenes=["cornell-box"], **run)
    evaluate.evaluate(evaluate.SUITES["mini"], 0.3, scenes=["cardioid"], **run)
    again = evaluate.evaluate(evaluate.SUITES["mini"], 0.3, scenes=["cardioid"], **run)
    doc = json.loads((tmp_path / "results.json").read_text())
    counts = {scene: sum(r["scene"] == scene for r in doc["samples"]) for scene in ("cornell-box", "cardioid")}
    assert counts["cornell-box"] >= 1 and counts["cardioid"] == sum(s.scene == "cardioid" for s in again.samples)
    # A different budget starts afresh.
    evaluate.evaluate(evaluate.SUITES["mini"], 0.2, scenes=["cardioid"], **run)
    doc = json.loads((tmp_path / "results.json").read_text())
    assert {r["scene"] for r in doc["samples"]} == {"cardioid"}


def test_mirror_pixels_are_scored_apart_against_the_mirror_limit(monkeypatch, tmp_path):
    """A case with `mirror_limit` adds the mirror pixels' errors against the
    limit to every sample (json, csv and a table of their own), leaving the
    ordinary scores as they were."""
    mirror = np.zeros((32, 32), bool)
    mirror[8:12] = True
    reference = np.full((32, 32, 3), 0.5, np.float32)
    limit = np.where(mirror[..., None], 2.0 * reference, reference).astype(np.float32)
    monkeypatch.setattr(evaluate, "reference_image", lambda scene, case, spp, cache: (reference, ~mirror))
    monkeypatch.setattr(evaluate, "mirror_reference",
                        lambda scene, ref, scored, cache: (limit, mirror, "a limit"))
    case = evaluate.Case("cardioid", "mirror", "ptracer+path", scored="no-specular-in-view",
                         mirror_limit=True)
    suite = evaluate.Suite("mirror-test", 32, 32, (case,), ("sppm-grid",))
    ev = evaluate.evaluate(suite, 0.3, log=lambda _l: None, out_dir=str(tmp_path))
    assert ev.samples and not ev.failed
    for s in ev.samples:
        assert math.isfinite(s.mirror_limit_relmse) and math.isfinite(s.mirror_limit_blurred_relmse)
        assert math.isfinite(s.relmse)
    # The render is near 0.5 or below where the limit is 1.0: about -50%.
    assert all(s.mirror_limit_bias < -0.3 for s in ev.samples)
    doc = json.loads((tmp_path / "results.json").read_text())
    assert "a limit" in doc["references"]["cardioid"]
    assert all(r["mirror_limit_bias"] is not None for r in doc["samples"])
    assert "mirror_limit_blurred_relmse" in (tmp_path / "results.csv").read_text().splitlines()[0]
    assert "Mirror pixels against the mirror limit" in (tmp_path / "summary.md").read_text()


FLOOR_XML = """<scene version="3.0.0">
    <sensor type="perspective"><float name="fov" value="60"/>
        <transform name="to_world"><lookat origin="0, 1, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="12"/></film>
    </sensor>
    <shape type="rectangle"><bsdf type="diffuse"/>
        <transform name="to_world"><rotate x="1" angle="-90"/></transform></shape>
    <emitter type="point"><point name="position" x="0" y="1" z="0"/></emitter>
</scene>
"""


def test_a_case_from_the_shared_folder_keeps_its_resolution_and_file_reference(monkeypatch, tmp_path):
    """The scene is loaded by path at its own 16x12 (not the suite's 32x32),
    scored against the EXR beside it; its pbrt file is handed to the methods."""
    from dosppm_core.film import write_exr
    (tmp_path / "case").mkdir()
    (tmp_path / "case" / "floor.xml").write_text(FLOOR_XML)
    write_exr(str(tmp_path / "case" / "ref.exr"), np.full((12, 16, 3), 0.5, np.float32))
    (tmp_path / "case" / "floor.pbrt").write_text("WorldBegin\n")
    seen = {}

    def fake_run(method, scene, budgets, seed, work, pbrt_file=None):
        seen.update(scene=scene, pbrt_file=pbrt_file)
        return [(budgets[-1], 0.1, 0, np.full((12, 16, 3), 0.6, np.float32))]
    monkeypatch.setattr(evaluate, "run_method", fake_run)
    monkeypatch.setattr(evaluate, "_warm_kernels", lambda: None)
    files = suites.SharedFiles("case/floor.xml", "case/ref.exr", "a made-up reference",
                                 pbrt="case/floor.pbrt")
    suite = evaluate.Suite("file-test", 32, 32, (evaluate.Case("floor", "a file case", "file",
                                                                files=files),), ("sppm-grid",))
    ev = evaluate.evaluate(suite, 0.3, log=lambda _l: None, shared=str(tmp_path))
    assert not ev.failed and not ev.skipped
    assert (seen["scene"].camera.width, seen["scene"].camera.height) == (16, 12)
    assert seen["pbrt_file"] == str(tmp_path / "case" / "floor.pbrt")
    assert ev.references["floor"] == "a made-up reference"
    assert [round(s.bias, 3) for s in ev.samples] == [0.2]
