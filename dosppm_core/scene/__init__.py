"""Scenes: what is rendered, and where it comes from.

    from dosppm_core.scene import Scene, load_scene
    scene = load_scene("cornell-box")            # or a .toml or Mitsuba .xml file

A `Scene` is flat arrays (triangles with one material id each, a material
table, a light table) and a camera; every source builds it through
`SceneBuilder`, which validates, so a bad scene gets the same one-line
`SceneError` whatever it came from.

==============  ==============================================================
module          what it holds
==============  ==============================================================
model           the data model: Scene, SceneBuilder, Camera, Material,
                MaterialTable, LightTable, SceneHeader, SceneError
loaders         `load_scene` (a built-in name, a TOML or a Mitsuba XML file)
                and `load_source` (also a triangle soup directory)
builtin         the registry of named scenes (`SCENES`, `DEFAULT`, `make`)
                and the Cornell-box and furnace scenes
cornell         the measured Cornell box: parts, materials, camera
suite           the failure-mode scenes (thin wall, far from origin, ...)
shapes          procedural meshes: boxes, ico spheres, torus knots
tomlfile        the TOML scene format (docs/scene-format.md) and mesh files
mitsuba/        the Mitsuba 3 (and Nori) XML importer, split by concern
soup, soupfile  triangle sources, and the on-disk triangle soup format
generate        the procedural office building, streamed to a soup;
                building_geometry holds its triangle-making helpers
==============  ==============================================================

The model imports no loader, so `model` can be used alone; this package
exports the model's names and the two loaders.
"""
from dosppm_core.scene.loaders import load_scene, load_source
from dosppm_core.scene.model import (
    DIFFUSE,
    GLASS,
    GLOSSY,
    LIGHT_DIRECTIONAL,
    LIGHT_ENV,
    LIGHT_POINT,
    LIGHT_SPOT,
    LIGHT_TRIANGLE,
    MATERIAL_KINDS,
    MIRROR,
    SPAWN_EPSILON,
    Camera,
    LightTable,
    Material,
    MaterialTable,
    Scene,
    SceneBuilder,
    SceneError,
    SceneHeader,
    light_table,
)

__all__ = [
    "Scene", "SceneBuilder", "SceneHeader", "SceneError", "Camera", "Material", "MaterialTable",
    "LightTable", "light_table", "MATERIAL_KINDS", "DIFFUSE", "MIRROR", "GLASS", "GLOSSY",
    "LIGHT_TRIANGLE", "LIGHT_POINT", "LIGHT_SPOT", "LIGHT_DIRECTIONAL", "LIGHT_ENV", "SPAWN_EPSILON", "load_scene", "load_source",
]
