"""What reading one scene's object tree accumulates: the `SceneBuilder`,
the ids, the render settings `Scene` has no home for, and the caches that
make one <bsdf> one material however often it is referenced."""
from __future__ import annotations

import os

from dosppm_core.scene.mitsuba.objects import Obj, Ref
from dosppm_core.scene.model import SceneBuilder


class ReaderState:
    """Shared by the plugin readers (shapes, bsdfs, emitters, sensors)."""

    def __init__(self, path: str, ids: dict, dialect: str, paths=()):
        self.builder = SceneBuilder(source=path, name=os.path.splitext(os.path.basename(path))[0])
        self.root_dir = os.path.dirname(os.path.abspath(path))
        self.paths = list(paths)            # <path> folders, the latest first
        self.ids = ids
        self.dialect = dialect
        self.settings: dict = {}
        self.bsdfs: dict = {}               # id(Obj) -> Material without emission
        self.material_ids: dict = {}        # (id(bsdf), id(emitter)) -> builder material id
        self.radiance: dict = {}            # id(area emitter) -> RGB radiance
        self.textures: dict = {}            # id(texture Obj) -> builder texture id
        self.images: dict = {}              # (real path, raw) -> texels read
        self.attribute_ids: dict = {}       # stand-in texture id -> (mesh attribute name, node)
        self.loose_area_emitters: list = []

    def children(self, obj: Obj, allowed) -> list:
        """Nested objects and references, each of a tag `allowed` here."""
        out = []
        for child in obj.children:
            target = child
            if isinstance(child, Ref):
                target = self.ids.get(child.id) or child.node.fail(f"unknown id {child.id!r}")
            if target.tag not in allowed:
                child.node.fail(f"not allowed inside {obj.node.label}")
            out.append(target)
        return out

    def single(self, obj: Obj, children: list, tag: str):
        """The one child of `tag` among `children`, or None."""
        found = [c for c in children if c.tag == tag]
        if len(found) > 1:
            obj.node.fail(f"more than one <{tag}>")
        return found[0] if found else None
