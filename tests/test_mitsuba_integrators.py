"""Issue 33, part 6: a Mitsuba scene's integrator renders as Mitsuba's
does. Mitsuba's `max_depth` counts path vertices after the camera, the
emitter's included (2: direct light only; -1: unbounded); ours counts
scattering events, so a file's max_depth M becomes our M - 1
(`settings.scene_settings`). `direct` is path at depth 2 and `ptracer`
carries path's transport. The same XML file is rendered by Mitsuba 3 and
by us, and the image means must agree."""
import importlib.util

import numpy as np
import pytest

import dosppm_core as dp
from dosppm_core.scene.model import SceneError
from dosppm_core.settings import RenderSettings, scene_settings
from services import config

# A closed diffuse box lit by a small one-sided area light under its
# ceiling: every bounce adds light, so depths 2 and 3 differ by about 13%.
BOX = """<scene version="3.0.0">
    <integrator type="{integrator}">{depth}</integrator>
    <sensor type="perspective">
        <float name="fov" value="80"/>
        <transform name="to_world"><lookat origin="0, -0.95, -0.2" target="0, 0, 0" up="0, 0, 1"/></transform>
        <film type="hdrfilm"><integer name="width" value="12"/><integer name="height" value="12"/>
            <rfilter type="box"/></film>
    </sensor>
    <shape type="cube">
        <boolean name="flip_normals" value="true"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.8 0.6 0.4"/></bsdf>
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><scale value="0.4"/><rotate x="1" angle="180"/><translate z="0.98"/></transform>
        <emitter type="area"><rgb name="radiance" value="5"/></emitter>
    </shape>
</scene>
"""


def _box(tmp_path, integrator: str, max_depth: int | None) -> str:
    depth = "" if max_depth is None else f'<integer name="max_depth" value="{max_depth}"/>'
    path = tmp_path / f"box_{integrator}_{max_depth}.xml"
    path.write_text(BOX.format(integrator=integrator, depth=depth))
    return str(path)


def test_mitsuba_depth_becomes_our_scattering_count():
    assert scene_settings({"integrator": "path", "max_depth": 2}) == {"max_depth": 1}
    assert scene_settings({"integrator": "ptracer", "max_depth": 8}) == {"max_depth": 7}
    assert scene_settings({"integrator": "path", "max_depth": -1}) == {"max_depth": RenderSettings.max_depth}
    assert scene_settings({"integrator": "path"}) == {"max_depth": RenderSettings.max_depth}
    assert scene_settings({"integrator": "direct"}) == {"max_depth": 1}
    assert scene_settings({}) == {} and scene_settings({"iterations": 3}) == {}   # a TOML [render] table
    with pytest.raises(ValueError, match="max_depth 0"):
        scene_settings({"integrator": "path", "max_depth": 0})
    with pytest.raises(ValueError, match="hide_emitters"):
        scene_settings({"integrator": "path", "hide_emitters": True})
    assert scene_settings({"integrator": "path", "hide_emitters": False}) == {"max_depth": RenderSettings.max_depth}
    with pytest.raises(ValueError, match="aov"):
        scene_settings({"integrator": "aov"})


def test_a_flag_overrides_the_scene_file_and_the_file_overrides_the_default():
    hints = {"integrator": "path", "max_depth": 3}
    assert config.render_settings({}, scene_hints=hints).max_depth == 2
    assert config.render_settings({"max_depth": 7}, scene_hints=hints).max_depth == 7
    assert config.render_settings({}, service=True, scene_hints=hints).max_depth == 2
    assert config.render_settings({}).max_depth == RenderSettings.max_depth


def test_the_api_takes_the_files_depth_unless_told(tmp_path):
    path = _box(tmp_path, "path", 2)
    one = np.asarray(dp.render(dp.load(path), iterations=40, seed=3))
    assert np.array_equal(one, np.asarray(dp.render(dp.load(path), iterations=40, seed=3, max_depth=1)))
    assert not np.array_equal(one, np.asarray(dp.render(dp.load(path), iterations=40, seed=3, max_depth=2)))
    with pytest.raises(SceneError, match="max_depth 0"):
        dp.render(dp.load(_box(tmp_path, "path", 0)), iterations=1)


@pytest.mark.reference
@pytest.mark.skipif(importlib.util.find_spec("mitsuba") is None, reason="mitsuba not installed")
@pytest.mark.parametrize("integrator, max_depth", [("path", 2), ("path", 3), ("ptracer", 2), ("ptracer", 3),
                                                   ("direct", None)])
def test_our_render_of_a_mitsuba_file_has_mitsubas_mean(tmp_path, integrator, max_depth):
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    path = _box(tmp_path, integrator, max_depth)
    theirs = np.asarray(mi.render(mi.load_file(path), spp=512, seed=0), dtype=np.float64).mean()
    ours = np.asarray(dp.render(dp.load(path), iterations=600, seed=1), dtype=np.float64).mean()
    # Seed noise of either mean is under 0.3%; a bounce more or less is 13%.
    assert ours == pytest.approx(theirs, rel=0.015)
    if max_depth == 3:
        fewer = np.asarray(mi.render(mi.load_file(_box(tmp_path, integrator, 2)), spp=512), np.float64).mean()
        assert theirs > 1.08 * fewer
