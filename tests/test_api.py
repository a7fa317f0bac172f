"""The Python API (`import dosppm_core as dp`): load from a name, a file or
a dict, render to a float32 image with its statistics, write it; and it is
the same renderer the command line and the evaluation run."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

import dosppm_core as dp
from dosppm_core.chunks.store import ChunkStore
from dosppm_core.chunks.subdivide import subdivide
from dosppm_core.film import read_exr
from dosppm_core.modes.osppm import OutOfCoreRenderer
from dosppm_core.modes import sppm
from dosppm_core.scene.generate import generate_building
from dosppm_core.scene.model import SceneError
from dosppm_core.scene.soup import SceneSource
from dosppm_core.settings import RenderSettings
from tests.helpers.paths import REPO

BOX = {
    "camera": {"position": [0, 1, -3], "look_at": [0, 1, 0], "fov": 50, "width": 24, "height": 16},
    "materials": {"white": {"type": "diffuse", "reflectance": [0.7, 0.7, 0.7]}},
    "shapes": [{"type": "box", "material": "white", "scale": [4, 4, 4], "translate": [0, 1, 0]}],
    "lights": [{"type": "point", "position": [0, 2, 0], "intensity": [50, 50, 50]}],
}


def test_load_takes_a_name_a_file_or_a_dict():
    assert dp.load("cornell-box", width=20, height=10).camera.width == 20
    knot = dp.load(os.path.join(REPO, "examples", "cornell.toml"))
    assert knot.triangle_count > 2000
    scene = dp.load(BOX)
    assert (scene.camera.width, scene.camera.height) == (24, 16) and scene.triangle_count == 12
    with pytest.raises(SceneError, match=r"scene dict: shapes\[0\]\.colour: unknown key"):
        dp.load({**BOX, "shapes": [{**BOX["shapes"][0], "colour": 1}]})


def test_render_is_the_library_renderer_with_its_statistics():
    scene = dp.load("cornell-box", width=16, height=16)
    image = dp.render(scene, iterations=2, seed=3, photons_per_iteration=20_000)
    assert image.shape == (16, 16, 3) and image.pixels.dtype == np.float32
    assert image.stats["iterations"] == 2 and image.stats["photons"] == 40_000
    assert image.stats["mode"] == "sppm" and image.stats["hit_points"] > 0
    same = sppm.render(scene, RenderSettings(seed=3, photons_per_iteration=20_000), iterations=2)
    np.testing.assert_array_equal(np.asarray(image), same.astype(np.float32))


def test_out_of_core_through_the_api_is_the_library_out_of_core_renderer(tmp_path):
    """mode="osppm" is OutOfCoreRenderer over the scene cut into `chunks`
    chunks (its correctness, chunked against unchunked: tests/test_osppm.py)."""
    scene = dp.load("cornell-box", width=16, height=16)
    four = dp.render(scene, iterations=3, mode="osppm", chunks=4, seed=1, photons_per_iteration=20_000)
    assert four.stats["mode"] == "osppm" and four.stats["photons"] == 60_000
    subdivide(SceneSource(scene), str(tmp_path / "s"), chunks=4)
    o = OutOfCoreRenderer(ChunkStore.open(str(tmp_path / "s")), RenderSettings(seed=1, photons_per_iteration=20_000))
    for _ in range(3):
        o.run_iteration()
    o.finish()
    np.testing.assert_array_equal(four.pixels, o.image().astype(np.float32))
    o.close()


def test_render_stops_hands_back_the_image_as_each_time_passes():
    scene = dp.load("cornell-box", width=16, height=16)
    images = list(dp.render_stops(scene, [0.3, 0.6], photons_per_iteration=20_000))
    assert [i.stats["stop"] for i in images] in ([0.3, 0.6], [0.6])   # one iteration may span both
    # The last time is a deadline: the render stops once another iteration
    # would not fit before it (0.59994 s once), not only after it.
    last = images[-1].stats
    assert last["seconds"] + last["seconds"] / last["iterations"] >= 0.6
    assert images[0].stats["photons"] <= images[-1].stats["photons"]


def test_bad_arguments_are_clear_errors():
    scene = dp.load("cornell-box", width=8, height=8)
    with pytest.raises(TypeError, match="unknown render setting 'radious'"):
        dp.render(scene, iterations=1, radious=2.0)
    with pytest.raises(ValueError, match="mode must be one of sppm, osppm"):
        dp.render(scene, iterations=1, mode="dosppm")
    with pytest.raises(ValueError, match="alpha must lie in"):
        dp.render(scene, iterations=1, alpha=2.0)


def test_write_exr_and_png(tmp_path):
    image = dp.render(dp.load(BOX), iterations=1, photons_per_iteration=10_000)
    dp.write(tmp_path / "a.exr", image)
    back, _ = read_exr(str(tmp_path / "a.exr"))
    np.testing.assert_array_equal(back, image.pixels)
    dp.write(tmp_path / "a.png", image, exposure=1.0)
    assert (tmp_path / "a.png").read_bytes().startswith(b"\x89PNG")
    with pytest.raises(ValueError, match="unknown image format '.jpg'"):
        dp.write(tmp_path / "a.jpg", image)


def test_load_and_render_open_a_soup_and_a_chunk_store_as_the_command_does(tmp_path, monkeypatch):
    """`dosppm render big/` renders a soup directory and a chunk store; so
    do dp.load and dp.render, out of core (issue 29). The soup is cut once,
    into the store cache the command uses; the image is the OSPPM renderer's
    over that store."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    soup = tmp_path / "big"
    generate_building(str(soup), triangles=20_000, lights=6, width=16, height=12)
    cut = dp.load(soup)
    assert isinstance(cut, ChunkStore) and cut.path.startswith(str(tmp_path / "cache"))
    assert dp.load(str(soup), width=8).path == cut.path          # cut once, then reused
    image = dp.render(cut, iterations=2, seed=4, photons_per_iteration=20_000)
    assert image.stats["mode"] == "osppm" and image.shape == (12, 16, 3) and image.stats["photons"] == 40_000
    store = dp.load(cut.path)             # the store itself, by its path
    again = dp.render(store.path, iterations=2, seed=4, photons_per_iteration=20_000)
    np.testing.assert_array_equal(again.pixels, image.pixels)
    o = OutOfCoreRenderer(ChunkStore.open(cut.path), RenderSettings(seed=4, photons_per_iteration=20_000),
                          memory_bytes=max(2 * store.budget_bytes, store.chunk_memory.max()))
    for _ in range(2):
        o.run_iteration()
    o.finish()
    np.testing.assert_array_equal(image.pixels, o.image().astype(np.float32))
    o.close()
    with pytest.raises(ValueError, match="chunk store renders chunk by chunk: mode 'osppm'"):
        dp.render(store, iterations=1, mode="sppm")


def test_a_path_that_is_not_a_scene_gets_the_commands_one_line_error(tmp_path):
    (tmp_path / "empty").mkdir()
    for path, why in ((tmp_path / "nothing", "no such file, and not a built-in scene"),
                      (tmp_path / "empty", "a directory, but neither a chunk store nor a triangle soup")):
        with pytest.raises(SceneError, match=why) as caught:
            dp.load(path)
        assert "\n" not in str(caught.value) and str(path) in str(caught.value)
        said = subprocess.run([sys.executable, "-P", "-m", "services.cli", "render", str(path), "--time", "1"],
                              capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=REPO))
        assert said.returncode != 0 and str(caught.value) in said.stderr, said.stderr
