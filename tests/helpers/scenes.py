"""Built-in scenes made small enough for a test."""
from __future__ import annotations

from dosppm_core.scene import builtin


def small_scene(name: str, size: int):
    """The built-in scene `name` rendered at size x size pixels."""
    scene = builtin.make(name)
    scene.camera.width = scene.camera.height = size
    return scene
