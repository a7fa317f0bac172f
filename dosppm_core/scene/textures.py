"""Textures: images and checkerboards a material's reflectance may read
instead of a constant colour, kept as flat arrays the kernels index.

A scene's textures are one `TextureTable`: every texel of every texture in
one float32 (N, 3) buffer of linear RGB, and per texture one row of `info`
(kind, first texel row, width, height, filter, wrap mode) and one of
`uv_map` (the affine to_uv transform). A checkerboard is two texels,
color0 then color1. The lookup (`kernels.texture`) follows Mitsuba 3's
`bitmap` and `checkerboard`:

* uv = to_uv(hit uv); a bitmap's texel (x, y) covers [x, x+1)/width by
  [y, y+1)/height, y counted from the image file's top row (Mitsuba's
  convention: v = 0 is the top of the picture, and its OBJ reader turns
  the file's v into 1 - v);
* bilinear: the four texels around uv * size - 0.5, nearest: the one at
  floor(uv * size); wrap modes repeat, mirror and clamp as Mitsuba's;
* 8-bit and 16-bit images are sRGB-decoded unless `raw` (Mitsuba's rule
  for colour images); EXR texels are linear and taken as they are.

This is the only module that imports Pillow (for PNG, JPEG, BMP and the
other 8-bit formats); EXR goes through `film.read_exr`.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from dosppm_core.scene.errors import SceneError

BITMAP, CHECKERBOARD = 0, 1
BILINEAR, NEAREST = 0, 1
FILTERS = {"bilinear": BILINEAR, "nearest": NEAREST}
REPEAT, MIRROR, CLAMP = 0, 1, 2
WRAP_MODES = {"repeat": REPEAT, "mirror": MIRROR, "clamp": CLAMP}
# Columns of `TextureTable.info`.
INFO_KIND, INFO_OFFSET, INFO_WIDTH, INFO_HEIGHT, INFO_FILTER, INFO_WRAP = range(6)
IDENTITY_UV = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


@dataclass
class Texture:
    """One texture before it joins the table: its texels (H, W, 3) linear
    RGB, top row first (a checkerboard: (1, 2, 3), color0 and color1)."""
    name: str
    kind: int
    texels: np.ndarray
    filter: int = BILINEAR
    wrap: int = REPEAT
    uv_map: tuple = IDENTITY_UV     # u' = a u + b v + c, v' = d u + e v + f

    @property
    def nbytes(self) -> int:
        return int(self.texels.size) * 4


def checkerboard(name: str, color0, color1, uv_map=IDENTITY_UV) -> Texture:
    """Mitsuba's checkerboard: color0 where the fractional parts of u and v
    are both at most 1/2 or both above, color1 elsewhere."""
    texels = np.array([[color0, color1]], np.float32).reshape(1, 2, 3)
    return Texture(name, CHECKERBOARD, texels, NEAREST, REPEAT, tuple(uv_map))


def bitmap(name: str, texels, filter_type: str = "bilinear", wrap_mode: str = "repeat",
           uv_map=IDENTITY_UV) -> Texture:
    """A bitmap texture of (H, W, 3) linear texels (top row first)."""
    texels = np.asarray(texels, np.float32)
    if texels.ndim != 3 or texels.shape[2] != 3 or texels.shape[0] < 1 or texels.shape[1] < 1:
        raise SceneError(f"texture {name!r}: expected (height, width, 3) texels, got {texels.shape}")
    if filter_type not in FILTERS:
        raise SceneError(f"texture {name!r}: filter_type must be one of {', '.join(FILTERS)}, "
                         f"got {filter_type!r}")
    if wrap_mode not in WRAP_MODES:
        raise SceneError(f"texture {name!r}: wrap_mode must be one of {', '.join(WRAP_MODES)}, "
                         f"got {wrap_mode!r}")
    return Texture(name, BITMAP, np.ascontiguousarray(texels), FILTERS[filter_type],
                   WRAP_MODES[wrap_mode], tuple(float(x) for x in uv_map))


@dataclass
class TextureTable:
    """Every texture of a scene as flat arrays (see the module docstring)."""
    info: np.ndarray      # int32 (K, 6)
    uv_map: np.ndarray    # float64 (K, 6)
    texels: np.ndarray    # float32 (N, 3)
    names: list

    @classmethod
    def empty(cls) -> "TextureTable":
        return cls(np.zeros((0, 6), np.int32), np.zeros((0, 6), np.float64),
                   np.zeros((0, 3), np.float32), [])

    @classmethod
    def from_textures(cls, textures: list[Texture]) -> "TextureTable":
        if not textures:
            return cls.empty()
        info = np.zeros((len(textures), 6), np.int32)
        offset, blocks, placed = 0, [], {}
        for k, t in enumerate(textures):
            h, w = t.texels.shape[:2]
            # Textures sharing one texel array (one image file read with
            # several filters or wrap modes) share one block.
            if id(t.texels) not in placed:
                placed[id(t.texels)] = offset
                blocks.append(t.texels.reshape(-1, 3))
                offset += h * w
            info[k] = (t.kind, placed[id(t.texels)], w, h, t.filter, t.wrap)
        if offset >= 2 ** 31:
            raise SceneError(f"textures hold {offset:,} texels: more than the int32 offsets allow")
        texels = np.concatenate(blocks).astype(np.float32)
        uv_map = np.array([t.uv_map for t in textures], np.float64).reshape(-1, 6)
        return cls(info, uv_map, texels, [t.name for t in textures])

    def __len__(self) -> int:
        return int(self.info.shape[0])

    def subset(self, ids) -> tuple["TextureTable", np.ndarray]:
        """The table of textures `ids` only, and the map old id -> new id
        (-1 for a texture left out), for a chunk that uses a few."""
        ids = np.unique(np.asarray(ids, np.int64))
        remap = np.full(len(self), -1, np.int32)
        remap[ids] = np.arange(len(ids), dtype=np.int32)
        parts, info, offset, placed = [], np.zeros((len(ids), 6), np.int32), 0, {}
        for j, k in enumerate(ids):
            a = int(self.info[k, INFO_OFFSET])
            if a not in placed:             # a block shared in the table stays shared
                n = int(self.info[k, INFO_WIDTH]) * int(self.info[k, INFO_HEIGHT])
                parts.append(self.texels[a:a + n])
                placed[a] = offset
                offset += n
            info[j] = self.info[k]
            info[j, INFO_OFFSET] = placed[a]
        texels = np.concatenate(parts) if parts else np.zeros((0, 3), np.float32)
        return TextureTable(info, self.uv_map[ids].copy(), texels,
                            [self.names[k] for k in ids]), remap


# -- image files -----------------------------------------------------------------
def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """The sRGB transfer curve, inverted (IEC 61966-2-1), as Mitsuba decodes."""
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def read_image(path: str, raw: bool = False) -> np.ndarray:
    """(H, W, 3) float32 linear texels of an image file, top row first: an
    EXR as stored, any format Pillow reads (PNG, JPEG, BMP, ...) scaled to
    [0, 1] and, unless `raw`, sRGB-decoded. Grey images are repeated into
    three channels and alpha is dropped. ValueError with a one-line reason
    if the file cannot be read."""
    if os.path.splitext(path)[1].lower() == ".exr":
        from dosppm_core.film import FilmError, read_exr
        try:
            rgb, _layers = read_exr(path)
        except FilmError as exc:
            raise ValueError(str(exc)) from None
        return np.ascontiguousarray(rgb, np.float32)
    return _read_pillow(path, raw)


def _read_pillow(path: str, raw: bool) -> np.ndarray:
    try:
        from PIL import Image, UnidentifiedImageError
    except ImportError:
        raise ValueError(f"{path}: reading this image needs Pillow (pip install Pillow)") from None
    try:
        with Image.open(path) as img:
            img.load()
            scale, arr = _pixels(img)
    except (OSError, UnidentifiedImageError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read image: {exc}") from None
    values = arr.astype(np.float64) / scale
    if values.ndim == 2:
        values = values[:, :, None]
    values = values[:, :, :3] if values.shape[2] >= 3 else np.repeat(values[:, :, :1], 3, axis=2)
    if not raw:
        values = srgb_to_linear(values)
    return np.ascontiguousarray(values, np.float32)


def _pixels(img):
    """(full scale, array) of a Pillow image: 8-bit modes as they are,
    16-bit greys by their maximum 65535, palettes expanded to RGB(A)."""
    if img.mode in ("I;16", "I;16B", "I;16L", "I"):
        return 65535.0, np.asarray(img, np.uint32)
    if img.mode in ("F",):
        raise ValueError("floating-point images other than EXR are unsupported")
    if img.mode not in ("L", "LA", "RGB", "RGBA"):
        img = img.convert("RGBA" if "A" in img.getbands() or "transparency" in img.info else "RGB")
    return 255.0, np.asarray(img, np.uint8)
