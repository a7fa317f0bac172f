"""Images on disk: OpenEXR for linear radiance, PNG for previews.

This is the only module that imports OpenEXR. EXR files hold the linear RGB
estimate plus optional single-channel float32 layers (per-pixel SPPM state
such as `radius` or `photon_count`), ZIP-compressed. PNG previews are
tone-mapped to 8-bit sRGB by a small encoder (zlib + struct), so the library
needs no imaging package.

Every writer goes through a temporary file in the target's folder and
`os.replace`, so a reader (a viewer polling a progressive render, another
process) never sees a half-written image.
"""
from __future__ import annotations

import os
import re
import secrets
import struct
import zlib

import numpy as np
import OpenEXR

_EXR_MAGIC = b"\x76\x2f\x31\x01"
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# Names the RGB estimate occupies, or that OpenEXR would group into it.
_RESERVED_LAYERS = {"R", "G", "B", "A", "RGB", "RGBA"}
# A dot would make OpenEXR treat the name as layer.channel and regroup it.
_LAYER_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class FilmError(OSError):
    """An image could not be read or written; the message is one line
    naming the file."""


# -- writing ---------------------------------------------------------------
def write_exr(path: str, rgb, layers: dict | None = None) -> None:
    """Write linear RGB (H, W, 3) and optional single-channel layers
    {name: (H, W)} as float32 EXR channels with ZIP compression."""
    path = os.fspath(path)
    channels = {"RGB": _rgb_float32(rgb, path)}
    height, width = channels["RGB"].shape[:2]
    for name, arr in (layers or {}).items():
        channels[name] = _layer_float32(name, arr, (height, width), path)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    def write(tmp: str) -> None:
        with OpenEXR.File(header, channels) as exr:
            exr.write(tmp)
    _atomic_write(path, write, ".exr")


def write_png(path: str, rgb, exposure: float = 0.0) -> None:
    """Write a tone-mapped 8-bit sRGB preview of linear RGB (H, W, 3):
    scale by 2**exposure (stops), clamp to [0, 1], apply the sRGB OETF."""
    write_png_rgb8(path, tonemap_srgb8(rgb, exposure))


def tonemap_srgb8(rgb, exposure: float = 0.0) -> np.ndarray:
    """Linear RGB -> uint8 sRGB; NaN becomes black, +Inf white."""
    x = np.asarray(rgb, dtype=np.float64) * (2.0 ** float(exposure))
    x = np.clip(np.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


def write_png_rgb8(path: str, u8) -> None:
    """Write an already-mapped uint8 image, (H, W, 3) RGB or (H, W, 4) RGBA."""
    path = os.fspath(path)
    img = np.asarray(u8)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] not in (3, 4) or 0 in img.shape:
        raise FilmError(f"{path}: expected a non-empty uint8 (H, W, 3|4) image, "
                        f"got {img.dtype} {img.shape}")
    data = encode_png(img)

    def write(tmp: str) -> None:
        with open(tmp, "xb") as f:
            f.write(data)
    _atomic_write(path, write, ".png")


def encode_png(img: np.ndarray) -> bytes:
    """PNG bytes of a uint8 (H, W, 3|4) image: filter type 0 on every row,
    one zlib-compressed IDAT chunk."""
    height, width, comps = img.shape
    color_type = 2 if comps == 3 else 6
    rows = np.ascontiguousarray(img).reshape(height, width * comps)
    raw = np.concatenate([np.zeros((height, 1), np.uint8), rows], axis=1).tobytes()
    ihdr = struct.pack(">IIBBBBB", width, height, 8, color_type, 0, 0, 0)
    return (_PNG_SIGNATURE + _png_chunk(b"IHDR", ihdr)
            + _png_chunk(b"IDAT", zlib.compress(raw, 6)) + _png_chunk(b"IEND", b""))


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    crc = zlib.crc32(kind + data) & 0xFFFFFFFF
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)


# -- reading ---------------------------------------------------------------
def read_exr(path: str) -> tuple[np.ndarray, dict]:
    """Read an EXR: (rgb float32 (H, W, 3), {layer name: float32 (H, W)}).
    RGBA files lose alpha; other channels become layers."""
    path = os.fspath(path)
    _check_exr_magic(path)
    try:
        with OpenEXR.File(path) as exr:
            # The channel dict empties when the block exits: copy inside.
            channels = {k: np.array(v.pixels, dtype=np.float32) for k, v in exr.channels().items()}
    except Exception as exc:  # OpenEXR raises bare RuntimeError
        raise FilmError(f"{path}: cannot read EXR: {one_line(exc)}") from None
    return _split_channels(channels, path)


def _check_exr_magic(path: str) -> None:
    """Fail early with a clear message; OpenEXR's own errors are vague and
    the C library also prints to stderr."""
    try:
        with open(path, "rb") as f:
            magic = f.read(4)
    except OSError as exc:
        raise FilmError(f"{path}: cannot read EXR: {exc.strerror or exc}") from None
    if magic != _EXR_MAGIC:
        raise FilmError(f"{path}: cannot read EXR: not an OpenEXR file")


def _split_channels(channels: dict, path: str) -> tuple[np.ndarray, dict]:
    if "RGB" in channels:
        rgb = channels.pop("RGB")
    elif "RGBA" in channels:
        rgb = channels.pop("RGBA")[..., :3]
    elif {"R", "G", "B"} <= channels.keys():
        rgb = np.stack([channels.pop(c) for c in "RGB"], axis=-1)
    else:
        raise FilmError(f"{path}: cannot read EXR: no RGB channels "
                        f"(has {', '.join(sorted(channels)) or 'none'})")
    layers = {k: v for k, v in channels.items() if v.ndim == 2}
    return np.ascontiguousarray(rgb, dtype=np.float32), layers


# -- helpers ---------------------------------------------------------------
def _rgb_float32(rgb, path: str) -> np.ndarray:
    arr = np.asarray(rgb)
    if arr.ndim != 3 or arr.shape[2] != 3 or 0 in arr.shape:
        raise FilmError(f"{path}: expected a non-empty (H, W, 3) RGB image, got shape {arr.shape}")
    # OpenEXR silently writes strided arrays wrong and rejects float64.
    return np.ascontiguousarray(arr, dtype=np.float32)


def _layer_float32(name, arr, shape: tuple, path: str) -> np.ndarray:
    if not isinstance(name, str) or not _LAYER_NAME.match(name) or name in _RESERVED_LAYERS:
        raise FilmError(f"{path}: invalid layer name {name!r} (letters, digits, '_'; "
                        f"not R, G, B, A)")
    layer = np.asarray(arr)
    if layer.ndim == 3 and layer.shape[2] == 1:
        layer = layer[..., 0]
    if layer.shape != shape:
        raise FilmError(f"{path}: layer {name!r} has shape {layer.shape}, image is {shape}")
    return np.ascontiguousarray(layer, dtype=np.float32)


def _atomic_write(path: str, write, suffix: str) -> None:
    """Run write(tmp) on a temporary file beside `path`, then rename it into
    place (atomic on POSIX within one file system). The name is unique but
    not made by mkstemp, whose 0600 mode would survive the rename."""
    folder, base = os.path.split(os.path.abspath(path))
    tmp = os.path.join(folder, f".{base}.{os.getpid()}-{secrets.token_hex(4)}.tmp{suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except Exception as exc:
        _remove_quietly(tmp)
        if isinstance(exc, FilmError):
            raise
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else one_line(exc)
        raise FilmError(f"{path}: cannot write: {reason}") from exc


def _remove_quietly(path: str) -> None:
    try:
        os.remove(path)
    except OSError:
        pass


def one_line(exc: BaseException) -> str:
    """An exception as one line, for errors that name a file or field."""
    return " ".join(str(exc).split()) or type(exc).__name__
