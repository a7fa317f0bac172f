"""`-D NAME=VALUE` on the commands that load a scene: a Mitsuba file's
$NAME over its <default>, as `mitsuba -D` (issue 33). Seen from outside,
in the image size and depth the file's parameters set."""
import os

import numpy as np

from dosppm_core.chunks.store import ChunkStore
from dosppm_core.film import read_exr
from tests.helpers.cli import run_dosppm

SCENE = """<scene version="3.0.0">
    <default name="res" value="4"/>
    <default name="depth" value="-1"/>
    <integrator type="path"><integer name="max_depth" value="$depth"/></integrator>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 0, -6" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="3"/></film>
    </sensor>
    <emitter type="point"><point name="position" value="0, 0, -5"/></emitter>
    <!-- A cube, not a rectangle: the service emits no photon in a flat scene (on main too). -->
    <shape type="cube"><bsdf type="diffuse"/></shape>
</scene>
"""


def _scene(tmp_path) -> str:
    path = tmp_path / "scene.xml"
    path.write_text(SCENE)
    return str(path)


def _width(exr: str) -> int:
    return read_exr(exr)[0].shape[1]


def test_render_in_one_process_takes_parameters(tmp_path):
    scene, out = _scene(tmp_path), str(tmp_path / "a.exr")
    done = run_dosppm("render", scene, "--mode", "sppm", "--iterations", "1", "--out", out, "-D", "res=7",
                      "-D", "depth=2", "--quiet")
    assert done.returncode == 0, done.stderr
    assert _width(out) == 7
    done = run_dosppm("render", scene, "--mode", "sppm", "--iterations", "1", "--out", out, "--quiet")
    assert done.returncode == 0 and _width(out) == 4       # the <default>


def test_the_service_and_subdivide_take_parameters(tmp_path):
    scene, out = _scene(tmp_path), str(tmp_path / "s.exr")
    done = run_dosppm("render", scene, "--chunks", "2", "--iterations", "2", "--tracers", "1", "--out", out,
                      "--store-cache", str(tmp_path / "stores"), "--http", "off", "-D", "res=6", "--quiet",
                      timeout=120)
    assert done.returncode == 0, done.stderr
    assert _width(out) == 6 and np.isfinite(read_exr(out)[0]).all()
    store = str(tmp_path / "store")
    done = run_dosppm("subdivide", scene, "--chunks", "2", "--out", store, "-D", "res=5", "-D", "depth=3")
    assert done.returncode == 0, done.stderr
    header = ChunkStore.open(store).header
    assert header.camera.width == 5 and header.render_settings["max_depth"] == 3


def test_bad_parameters_are_one_line_errors(tmp_path):
    scene = _scene(tmp_path)
    done = run_dosppm("render", scene, "--mode", "sppm", "-D", "res", "--out", os.devnull)
    assert done.returncode == 2 and "expected NAME=VALUE" in done.stderr
    done = run_dosppm("render", "cornell-box", "--mode", "sppm", "-D", "res=3", "--out", str(tmp_path / "x.exr"))
    assert done.returncode != 0 and "only a Mitsuba .xml file takes them" in done.stderr
    done = run_dosppm("render", scene, "--mode", "sppm", "-D", "nosuch=3", "--out", str(tmp_path / "x.exr"))
    assert done.returncode != 0 and "nosuch" in done.stderr and len(done.stderr.strip().splitlines()) == 1
