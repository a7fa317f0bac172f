"""Test helpers shared by the material, light and kernel tests: a Mitsuba scene
file made of parts, a texture of four coloured quadrants, a one-triangle
chunk's textures, and the same scene rendered by SPPM and by OSPPM from
chunks, equal up to float noise; the arrays of a kernel's nested outputs."""
from __future__ import annotations

import numpy as np

from dosppm_core.modes.osppm import OutOfCoreRenderer
from dosppm_core.modes.sppm import Renderer
from dosppm_core.settings import RenderSettings
from tests.helpers.chunks import MemoryChunks, root_box, uniform_tree


def mitsuba_scene(tmp_path, emitter: str, shapes: str, size=32, origin="0, 0.3, 4", target="0, 0, 0",
                  up="0, 1, 0", fov=35, name="scene.xml") -> str:
    """A scene file at tmp_path/name: the emitter, the shapes, a camera at
    `origin` looking at `target` (box filter, size x size pixels)."""
    text = f"""<scene version="3.0.0">
    {emitter}
    <sensor type="perspective">
        <float name="fov" value="{fov}"/>
        <transform name="to_world"><lookat origin="{origin}" target="{target}" up="{up}"/></transform>
        <sampler type="independent"><integer name="sample_count" value="64"/></sampler>
        <film type="hdrfilm"><integer name="width" value="{size}"/><integer name="height" value="{size}"/>
            <rfilter type="box"/></film>
    </sensor>
    {shapes}
</scene>"""
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def floor_and_wall(floor_bsdf: str, spot_target="0,0,0", cutoff=25, beam=20, far=False) -> str:
    """Mitsuba XML: a 4 x 4 floor of `floor_bsdf` at z = 0 under a narrow
    spot (at 1,0,3 aiming at `spot_target`), and a wall at x = -2 the spot
    does not reach, so that all the wall's light comes off the floor; seen
    from the side, 24 x 24 pixels, paths of depth 3. `far`: a checkerboard
    diffuse plane far off (texture 0 of the scene, in another chunk)."""
    far_plane = ("""<shape type="rectangle"><transform name="to_world"><translate x="-12"/></transform>
    <bsdf type="diffuse"><texture name="reflectance" type="checkerboard"/></bsdf></shape>
  """ if far else "")
    return f"""<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective"><float name="fov" value="50"/>
    <transform name="to_world"><lookat origin="2.5,0,1.2" target="-2,0,0.6" up="0,0,1"/></transform>
    <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="24"/>
      <rfilter type="box"/></film>
  </sensor>
  {far_plane}<shape type="rectangle"><transform name="to_world"><scale value="2"/></transform>
    {floor_bsdf}</shape>
  <shape type="rectangle"><transform name="to_world"><scale value="2"/><rotate y="1" angle="90"/>
    <translate x="-2" z="2"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.8"/></bsdf></shape>
  <emitter type="spot">
    <transform name="to_world"><lookat origin="1,0,3" target="{spot_target}" up="0,1,0"/></transform>
    <float name="cutoff_angle" value="{cutoff}"/><float name="beam_width" value="{beam}"/>
    <rgb name="intensity" value="80"/>
  </emitter>
</scene>
"""


def quadrants() -> np.ndarray:
    """(8, 8, 3) 8-bit values: red, green, blue and yellow quadrants, so an
    image mirrored or turned shows."""
    texels = np.zeros((8, 8, 3))
    texels[:4, :4] = (255, 40, 40)
    texels[:4, 4:] = (40, 255, 40)
    texels[4:, :4] = (40, 40, 255)
    texels[4:, 4:] = (255, 255, 40)
    return texels


def one_triangle_chunk(scene, material: int):
    """A chunk holding one triangle of `material`, with the textures it
    needs attached: (chunk, its materials table, its texture table)."""
    from dosppm_core.chunks.store import ChunkGeometry
    from dosppm_core.chunks.textures import attach_textures, chunk_surface_textures
    chunk = ChunkGeometry(np.eye(3, dtype=np.float32), np.array([[0, 1, 2]], np.int32),
                          np.array([material], np.int32), np.zeros(1, np.int32), np.zeros((3, 2), np.float32))
    chunk = attach_textures(chunk, scene.header())
    mats, table = chunk_surface_textures(chunk, scene.header())
    return chunk, mats, table


def sppm_and_osppm_images(scene, provider, settings: RenderSettings, iterations: int):
    """(SPPM's image of `scene`, OSPPM's from the chunks of `provider`),
    each after `iterations` iterations with `settings`."""
    images = []
    for r in (Renderer(scene, settings), OutOfCoreRenderer(provider, settings, pipelined=False)):
        try:
            for _ in range(iterations):
                r.run_iteration()
            images.append(np.asarray(r.image()))
        finally:
            r.close()
    return images[0], images[1]


def assert_equal_up_to_float_noise(img, ref) -> None:
    """At most 2% of pixels off by more than 1e-4 (relative), none by 1%:
    chunks change float sums' order, not which paths are traced."""
    rel = np.abs(img - ref) / np.maximum(ref, 1e-6 * ref.max())
    assert np.mean(rel > 1e-4) < 0.02, f"{np.mean(rel > 1e-4):.2%} of pixels differ"
    assert rel.max() < 0.01, rel.max()


def assert_chunks_render_the_scene(scene, cells, iterations=2, box=None) -> None:
    """OSPPM over a uniform grid of `cells` chunks of `box` (default: the
    scene's root box) renders what SPPM does."""
    provider = MemoryChunks(scene, uniform_tree(root_box(scene) if box is None else box, cells))
    ref, img = sppm_and_osppm_images(scene, provider, RenderSettings(seed=5, photons_per_iteration=30_000),
                                     iterations)
    assert_equal_up_to_float_noise(img, ref)


def leaves(t):
    """The arrays of a kernel's nested tuple of outputs, in order (to compare two kernels' results)."""
    for x in t:
        if isinstance(x, tuple):
            yield from leaves(x)
        else:
            yield x
