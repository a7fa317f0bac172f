"""Whole-renderer behaviour: closed-form radiance, consistency, determinism,
the light-leak side test and the command line."""
import json
import math

import numpy as np
import pytest

from dosppm_core.modes.sppm import Renderer, render
from dosppm_core.scene import builtin
from dosppm_core.scene.model import Camera, Material, SceneBuilder
from dosppm_core.settings import RenderSettings
from tests.helpers.scenes import small_scene


def furnace_expected(albedo: float, intensity: float, depth: int) -> float:
    """rho I / (pi R^2) * sum_{k<D} rho^k for R = 1 (see builtin.furnace_sphere)."""
    return albedo * intensity / math.pi * sum(albedo ** k for k in range(depth))


@pytest.mark.parametrize("albedo", [0.3, 0.7])
def test_furnace_sphere_mean_converges_to_closed_form(albedo):
    scene = builtin.furnace_sphere(albedo=albedo, intensity=2.0)
    img = render(scene, RenderSettings(photons_per_iteration=200_000), iterations=8)
    # The default ends paths by Russian roulette alone: the whole series
    # (the depth limit leaves out rho^256 of it).
    expected = furnace_expected(albedo, 2.0, depth=RenderSettings().max_depth)
    assert np.all(np.isfinite(img))
    # Pixel estimates share photons within a radius, so the image mean has
    # roughly the noise of ~50 independent pixels at ~1.5%: 1.5% is > 3 sigma.
    assert img.mean() == pytest.approx(expected, rel=0.015)


@pytest.mark.parametrize("name", ["cornell-caustic", "cornell-glass", "glass-small-light", "thin-wall"])
def test_the_depth_limit_never_loses_light(name):
    """With the same seed every path draws the same numbers whatever the
    limit, so the default depth limit and a practically unlimited one
    render the same photons up to the limit: the images agree unless a
    path deeper than that would have lit a pixel. Glass traps some photons
    by total internal reflection until the limit, but they light nothing."""
    scene = small_scene(name, 24)
    a = render(scene, RenderSettings(photons_per_iteration=100_000), iterations=2)
    b = render(scene, RenderSettings(photons_per_iteration=100_000, max_depth=100_000), iterations=2)
    # Measured at 256: at most 3.2e-5 of the brightest pixel and of the mean
    # (cornell-glass); at 64 it was 1.7e-3 of the mean (glass-small-light).
    assert np.abs(a - b).max() <= 1e-4 * a.max()
    assert a.mean() == pytest.approx(b.mean(), rel=1e-4)


def test_depth_limit_truncates_the_series():
    scene = builtin.furnace_sphere(albedo=0.8)
    shallow = render(scene, RenderSettings(max_depth=2), iterations=6).mean()
    assert shallow == pytest.approx(furnace_expected(0.8, 1.0, 2), rel=0.02)


def test_error_falls_as_photons_grow():
    scene = builtin.furnace_sphere(albedo=0.5)
    expected = furnace_expected(0.5, 1.0, 10)
    r = Renderer(scene, RenderSettings(photons_per_iteration=50_000))
    errors = []
    for target in (2, 8, 32):
        while r.iteration < target:
            r.run_iteration()
        errors.append(float(np.sqrt(np.mean((r.image() - expected) ** 2))))
    r.close()
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.5 * errors[0]


def test_same_seed_same_image_and_other_seed_differs():
    scene = small_scene("cornell-box", 48)
    settings = dict(photons_per_iteration=30_000)
    a = render(scene, RenderSettings(seed=7, **settings), iterations=2)
    b = render(scene, RenderSettings(seed=7, **settings), iterations=2)
    c = render(scene, RenderSettings(seed=8, **settings), iterations=2)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def thin_wall_scene(side_test_width: int = 32):
    """Two rooms sharing one zero-thickness wall at z = 0: a light in the
    room z < 0, the camera in the dark room z > 0 looking at the wall."""
    b = SceneBuilder(name="thin-wall")
    b.add_material(Material("white", "diffuse", (0.8, 0.8, 0.8)))
    b.add_material(Material("lamp", "diffuse", (0.0, 0.0, 0.0), emission=(20.0, 20.0, 20.0)))
    box = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                    [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], float)
    quads = [(0, 1, 2, 3), (4, 7, 6, 5), (0, 4, 5, 1), (3, 2, 6, 7), (0, 3, 7, 4), (1, 5, 6, 2)]
    faces = [f for q in quads for f in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))]
    b.add_mesh(box, faces, "white", "box")   # two-sided, so inward or outward does not matter
    wall = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    b.add_mesh(wall, [(0, 1, 2), (0, 2, 3)], "white", "wall")
    lamp = np.array([[-0.2, 0.99, -0.6], [0.2, 0.99, -0.6], [0.2, 0.99, -0.2], [-0.2, 0.99, -0.2]])
    b.add_mesh(lamp, [(0, 1, 2), (0, 2, 3)], "lamp", "lamp")   # CCW from below: faces -y
    b.camera = Camera((0, 0, 0.9), (0, 0, 0), (0, 1, 0), 60, side_test_width, side_test_width)
    return b.build()


def test_thin_wall_does_not_leak_light():
    scene = thin_wall_scene()
    # A radius as large as a tenth of the room: without the side test the
    # lit side's photons would light the dark side of the wall.
    img = render(scene, RenderSettings(radius=0.2, photons_per_iteration=100_000), iterations=3)
    assert img.max() == 0.0
    scene.camera.position, scene.camera.look_at = (0, 0, -0.9), (0, 0, 0)
    lit = render(scene, RenderSettings(radius=0.2, photons_per_iteration=100_000), iterations=3)
    assert lit.mean() > 0.01


def test_cli_render_writes_exr_png_and_log(tmp_path):
    from dosppm_core.film import read_exr
    from services.cli.main import main
    out = tmp_path / "img.exr"
    log = tmp_path / "progress.jsonl"
    code = main(["render", "cornell-box", "--mode", "sppm", "--iterations", "2", "--width", "24", "--height", "16",
                 "--photons-per-iteration", "20000", "--out", str(out), "--log", str(log), "--quiet"])
    assert code == 0
    rgb, layers = read_exr(str(out))
    assert rgb.shape == (16, 24, 3) and np.all(np.isfinite(rgb)) and rgb.mean() > 0
    assert set(layers) >= {"radius", "photon_count"}
    assert (tmp_path / "img.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert [r["iteration"] for r in records] == [1, 2]
    assert records[-1]["photons"] == 40_000


def test_cli_bad_scene_is_one_line_error(tmp_path, capsys):
    from services.cli.main import main
    assert main(["render", str(tmp_path / "missing.toml"), "--mode", "sppm", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "missing.toml" in err and "\n" not in err


def test_dosppm_render_gives_each_local_tracer_its_memory(monkeypatch):
    """`dosppm render --memory` bounds every tracer process it starts, as
    `dosppm worker --memory` does (it used to reach only --mode osppm)."""
    from services import local
    from services.cli import render as render_cli
    from services.cli.main import main
    seen = {}
    monkeypatch.setattr(render_cli, "run_server", lambda scene, v, **kw: seen.update(v) or 0)
    assert main(["render", "cornell-box", "--tracers", "2", "--memory", "200MiB", "--time", "1"]) == 0
    assert seen["memory"] == "200MiB"
    started = []
    monkeypatch.setattr(local.subprocess, "Popen", lambda cmd, env: started.append(cmd))
    local._spawn_tracers(2, "tcp://127.0.0.1:5555", "/store", 2, {"--memory": seen["memory"]})
    assert len(started) == 2 and all(c[c.index("--memory") + 1] == "200MiB" for c in started)
    local._spawn_tracers(1, "tcp://127.0.0.1:5555", "/store", 2, {"--memory": None})
    assert "--memory" not in started[-1]
