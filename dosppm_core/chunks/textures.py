"""Textures out of core: a chunk carries only the textures its triangles
read, in its own file (so they are checked by its SHA-256 and fetched
with it), and their bytes count in its memory estimate; the store's
header keeps every texture's info row and to_uv map but no texels.

A chunk cut in memory (tests, `MemoryChunks`) carries none and reads the
scene header's full table instead."""
from __future__ import annotations

import dataclasses

import numpy as np

from dosppm_core.chunks.store import ChunkGeometry
from dosppm_core.scene.model import SceneHeader
from dosppm_core.scene.textures import TextureTable


# The material columns that name a texture: the colour, a mask's opacity,
# a blend's weight, a normal map and a bump map, a rough conductor's alpha_u
# and alpha_v (`scene.model.Material`).
TEXTURE_COLUMNS = ("texture", "opacity_texture", "blend_texture", "normal_map", "bump_map",
                   "alpha_u_texture", "alpha_v_texture")


def _reachable(materials, used) -> np.ndarray:
    """The materials `used` and the parts of the blends among them, to any depth."""
    seen = set(int(m) for m in used)
    todo = list(seen)
    while todo:
        for part in materials.blend[todo.pop()]:
            if part >= 0 and int(part) not in seen:
                seen.add(int(part))
                todo.append(int(part))
    return np.array(sorted(seen), np.int64)


def attach_textures(geometry: ChunkGeometry, header: SceneHeader) -> ChunkGeometry:
    """`geometry` with the textures its triangles' materials read (a subset
    of the header's table, with their ids in it): colours, masks'
    opacities, blends' weights, normal and bump maps, and those of the
    blends' parts."""
    table, mats = header.textures, header.materials
    if not len(table) or not len(geometry.tri_material):
        return geometry
    reached = _reachable(mats, np.unique(geometry.tri_material))
    used = np.concatenate([getattr(mats, c)[reached] for c in TEXTURE_COLUMNS])
    ids = np.unique(used[used >= 0]).astype(np.int32)
    if not len(ids):
        return geometry
    sub, _ = table.subset(ids)
    return dataclasses.replace(geometry, tex_ids=ids, tex_info=sub.info, tex_uv=sub.uv_map,
                               texels=sub.texels)


def store_header(header: SceneHeader) -> SceneHeader:
    """The header a store's manifest keeps: the textures without texels
    (the chunks hold those), so the server and every tracer's copy stay
    small however large the scene's images."""
    t = header.textures
    if not len(t.texels):
        return header
    bare = TextureTable(t.info, t.uv_map, np.zeros((0, 3), np.float32), list(t.names))
    return dataclasses.replace(header, textures=bare)


def chunk_surface_textures(geometry: ChunkGeometry, header: SceneHeader):
    """(MaterialTable, TextureTable) a resident chunk's kernels read: the
    chunk's own textures, with every texture column renumbered into them,
    when it carries them; the header's table when it holds the texels; else
    none (-1 in every column: a texture the chunk lacks is never indexed
    out of bounds)."""
    mats = header.materials
    if len(geometry.tex_ids):
        local = np.full(len(header.textures), -1, np.int32)
        local[geometry.tex_ids] = np.arange(len(geometry.tex_ids), dtype=np.int32)
        cols = {c: np.where(getattr(mats, c) >= 0, local[np.maximum(getattr(mats, c), 0)], -1)
                .astype(np.int32) for c in TEXTURE_COLUMNS}
        return (dataclasses.replace(mats, **cols),
                TextureTable(geometry.tex_info, geometry.tex_uv, geometry.texels, []))
    if len(header.textures.texels):
        return mats, header.textures
    cols = {c: np.full(len(mats.texture), -1, np.int32) for c in TEXTURE_COLUMNS}
    return dataclasses.replace(mats, **cols), TextureTable.empty()
