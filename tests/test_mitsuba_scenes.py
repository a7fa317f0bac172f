"""Issue 33, part 6: Mitsuba 3's own render-test scenes
(../shared/scenes/mitsuba-data/tests/scenes), scored as Mitsuba scores its
renderer (harness/render_test.py, benchmarks/mitsuba_scenes.py).

Every one of the 41 scenes is in exactly one list below. When a feature
lands and a scene starts to load, `test_refused_scenes_still_refuse`
fails and names it: move it to CLAIMED if `python
benchmarks/mitsuba_scenes.py --score --only NAME` says it passes, else to
LOADS with the reason. A claimed scene that refuses or fails the scorer
fails here."""
import os
import re

import pytest

from tests.helpers.paths import REPO, SHARED_SCENES, needs_shared_scenes

ROOT = os.path.join(SHARED_SCENES, "mitsuba-data", "tests", "scenes")

# Load, render and pass the scorer, in one process and through the service in 2 chunks.
CLAIMED = [
    "bsdf_spheres/test_textured_diffuse_path.xml",
    "floating_sphere/test_directional_direct.xml",
    "instancing/test_instancing_path.xml",
    "mesh_attributes/test_mesh_attributes_3_face_direct.xml",
    "mesh_attributes/test_mesh_attributes_3_vertex_direct.xml",
    "bsdf_spheres/test_roughplastic_linear_path.xml",
    "bsdf_spheres/test_roughplastic_nonlinear_path.xml",
    "bsdf_spheres/test_normalmap_path.xml",
    "bsdf_spheres/test_bumpmap_path.xml",
    "bsdf_spheres/test_envmap_path.xml",
    "mesh_attributes/test_mesh_attributes_1_face_direct.xml",
    "spot_light/test_spot_direct.xml",
    # Pass since render_test judges pixels our seeds render exactly (a white
    # background, a projector's lit square) as Mitsuba's test judges its own
    # render (see its module doc); texture_interp's and projector_textured's
    # Gaussian-filter tails pass under Mitsuba's variance floor.
    "orthographic_sensor/test_orthographic_path.xml",
    "projector/test_projector_constant_direct.xml",
    "projector/test_projector_textured_direct.xml",
    "texture_interp/test_texture_interp_direct.xml",
    "bsdf_spheres/test_constant_path.xml",
    "various_emitters/test_various_emitters_ptracer.xml",
    "bsdf_spheres/test_normalmap_roughconductor_path.xml",
    # Service: z-pass 100.00%, bias +0.92% (one process failed at 87.18%,
    # -0.28% before the alphas were read as Mitsuba's checkerboard eval_1).
    "bsdf_spheres/test_textured_roughconductor_path.xml",
    # With smooth shading normals: one process z-pass 99.86%, mean -0.92%
    # (16 seeds); service z-pass 100%, mean -0.42% (4 seeds).
    "participating_media/test_surf_area_light_volpath.xml",
]
# Load but are not claimed to pass yet: scene -> why (measured figures).
LOADS = {
    # The service renders these as one process does: at the service's seeds
    # (101-104) one process's mean is off by as much (below), a tracer's
    # chunks give SPPM's image bit for bit, and test_smooth_normals checks
    # the service against SPPM. The bias bound fails on seed noise: a few
    # highlight pixels carry it, and 4 seeds' mean has a standard error over
    # 1%. Figures: 16 seeds in one process, 4 through the service, the sd
    # of one seed's mean over 48 one-process seeds, and their mean +- its
    # standard error.
    # Smooth normals: z-pass 99.99%, mean -0.63% (+4.24% with face normals,
    # as Mitsuba's own render with face_normals); service z-pass 100%, mean
    # -1.88% (one process at 101-104: -1.92%); per seed sd 2.9%, mean over
    # 48 seeds -0.22% +- 0.42%.
    "bsdf_spheres/test_roughdielectric_path.xml": "service mean -1.9%: seed noise (sd 2.9% a seed)",
    "infinite_mirrors/scene_path.xml": "no refs/scene_ref_rgb.exr: Mitsuba's own test skips it",
    # Smooth normals: z-pass 100%, mean +0.81% (faceted: +1.4% +- 0.5%, the
    # conductor sphere's reflection of the light +5.2%); service z-pass 100%,
    # mean -2.48% (one process at 101-104: -2.76%, 2 chunks drained: bit
    # for bit); per seed sd 3.3%, 85% of it in 8 highlight pixels; mean over
    # 48 seeds +0.54% +- 0.48%.
    "bsdf_spheres/test_arealight_path.xml": "service mean -2.5%: seed noise (sd 3.3% a seed)",
    # Smooth normals: z-pass 100%, mean +1.66% (16 seeds; one highlight
    # pixel of the point light on the alpha 0.05 rough conductor); per seed
    # sd 6.5%, mean over 48 seeds -0.16% +- 0.93%.
    "bsdf_spheres/test_pointlight_path.xml": "mean +1.7%: seed noise (sd 6.5% a seed)",
    # Anisotropic GGX (0.25, 0.05) under the identity normal map: one
    # process (16 seeds) z-pass 100.00%, bias -0.00%; through the service
    # (4 seeds) z-pass 100.00% but bias -1.04% (one process at 101-104:
    # -1.38%); per seed sd 1.3%, mean over 48 seeds -0.11% +- 0.19%.
    "bsdf_spheres/test_normalmap_identity_roughconductor_path.xml": "service bias -1.04%: seed noise",
}
# Refused, with the element the one-line error names (the first outside our subset),
# to its first attribute.
REFUSED = {
    "bsdf_spheres/test_texturedprincipled1_path.xml": '<bsdf type="principled"',
    "bsdf_spheres/test_texturedprincipled2_path.xml": '<bsdf type="principled"',
    "bsdf_spheres/test_texturedprincipledthin_path.xml": '<bsdf type="principledthin"',
    "participating_media/test_hetero_sigmat_albedo_volpath.xml": '<medium type="heterogeneous"',
    "participating_media/test_hetero_sigmat_volpath.xml": '<medium type="heterogeneous"',
    "participating_media/test_hetero_spectral_sigmat_no_scattering_volpath.xml": '<medium type="heterogeneous"',
    "participating_media/test_hetero_spectral_sigmat_volpathmis.xml": '<medium type="heterogeneous"',
    "participating_media/test_homo_area_light_volpath.xml": '<medium type="homogeneous"',
    "participating_media/test_homo_dielectric_envmap_volpath.xml": '<medium type="homogeneous"',
    "participating_media/test_homo_emitter_inside_medium_volpath.xml": '<medium type="homogeneous"',
    "participating_media/test_homo_null_envmap_volpath.xml": '<medium type="homogeneous"',
    "participating_media/test_homo_obj_inside_medium_volpath.xml": '<medium type="homogeneous"',
    "participating_media/test_homo_roughdielectric_spot_volpath.xml": '<medium type="homogeneous"',
    "participating_media/test_homo_spectral_sigmat_volpathmis.xml": '<medium type="homogeneous"',
    "various_shapes/test_various_shapes_path.xml": '<shape type="serialized"',
}


def _survey():
    import importlib.util
    spec = importlib.util.spec_from_file_location("mitsuba_scenes",
                                                  os.path.join(REPO, "benchmarks", "mitsuba_scenes.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _path(name: str) -> str:
    if not os.path.isdir(ROOT):
        pytest.skip("../shared/scenes/mitsuba-data (beside the checkout) absent")
    return os.path.join(ROOT, name)


@needs_shared_scenes
def test_every_scene_is_in_one_list():
    names = [os.path.relpath(p, ROOT) for p in _survey().scene_files(_path(""))]
    listed = CLAIMED + list(LOADS) + list(REFUSED)
    assert len(names) == 41 and sorted(listed) == sorted(names), set(names) ^ set(listed)


@needs_shared_scenes
@pytest.mark.parametrize("name", sorted(REFUSED))
def test_refused_scenes_still_refuse(name):
    """A one-line error naming the file (that exists), the line and the element."""
    message = _survey().try_load(_path(name))
    assert message is not None, f"{name} loads now: move it to CLAIMED or LOADS"
    found = re.match(r"^(.+?\.xml):(\d+): (<\w+ \w+=\"[^\"]*\")[^\n]*: [^\n]+$", message)
    assert found and "\n" not in message, message
    assert os.path.isfile(found[1]) and int(found[2]) >= 1, message
    assert found[3] == REFUSED[name], f"{name} now stops at {found[3]}: update REFUSED ({message})"


@needs_shared_scenes
@pytest.mark.reference
@pytest.mark.parametrize("name", CLAIMED)
def test_claimed_scenes_pass_in_one_process(name):
    survey = _survey()
    refusal = survey.try_load(_path(name))
    assert refusal is None, f"a claimed scene refuses: {refusal}"
    entry = survey.score_scene(_path(name), service_seeds=0)
    assert entry["sppm"]["passed"], entry


@needs_shared_scenes
@pytest.mark.reference
@pytest.mark.slow
@pytest.mark.parametrize("name", CLAIMED)
def test_claimed_scenes_pass_through_the_service_in_chunks(name, tmp_path):
    from dosppm_core.film import read_exr
    from harness import render_test
    survey = _survey()
    path = _path(name)
    ref, var = (read_exr(f)[0] for f in survey.reference_files(path))
    n = survey.iterations_per_seed(ref.shape[0] * ref.shape[1], survey.SEEDS, survey.MIN_ITERATIONS)
    images, chunks = survey.render_service(path, [101, 102, 103, 104], n, str(tmp_path))
    s = render_test.score(images, ref, var)
    assert chunks >= 2 and s.passed, (chunks, s)
