"""EXR and PNG files: round trips, layers, atomic writes, clear errors."""
import os
import struct
import zlib

import numpy as np
import pytest

from dosppm_core.film import FilmError, read_exr, tonemap_srgb8, write_exr, write_png, write_png_rgb8


def _decode_png(path):
    """Minimal PNG decoder for filter-0, 8-bit RGB/RGBA files (what we write)."""
    data = open(path, "rb").read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, chunks = 8, {}
    while pos < len(data):
        (length,), kind = struct.unpack(">I", data[pos:pos + 4]), data[pos + 4:pos + 8]
        body = data[pos + 8:pos + 8 + length]
        crc = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])[0]
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF
        chunks[kind] = chunks.get(kind, b"") + body
        pos += 12 + length
    w, h, depth, color_type = struct.unpack(">IIBB", chunks[b"IHDR"][:10])
    comps = {2: 3, 6: 4}[color_type]
    rows = np.frombuffer(zlib.decompress(chunks[b"IDAT"]), np.uint8).reshape(h, 1 + w * comps)
    assert depth == 8 and np.all(rows[:, 0] == 0)
    return rows[:, 1:].reshape(h, w, comps)


def test_exr_round_trip_with_layers(tmp_path):
    rng = np.random.default_rng(1)
    rgb = rng.random((7, 5, 3)) * 100.0          # float64 in, float32 out
    radius = rng.random((7, 5)).astype(np.float32)
    count = np.arange(35, dtype=np.uint32).reshape(7, 5)
    path = str(tmp_path / "img.exr")
    write_exr(path, rgb, {"radius": radius, "photon_count": count})
    back, layers = read_exr(path)
    assert back.dtype == np.float32 and back.shape == (7, 5, 3)
    np.testing.assert_array_equal(back, rgb.astype(np.float32))
    assert set(layers) == {"radius", "photon_count"}
    np.testing.assert_array_equal(layers["radius"], radius)
    np.testing.assert_array_equal(layers["photon_count"], count.astype(np.float32))


def test_exr_non_contiguous_input_is_written_correctly(tmp_path):
    rng = np.random.default_rng(2)
    big = rng.random((12, 10, 4)).astype(np.float32)
    rgb = big[::2, ::-1, 1:]                      # strided, reversed, sliced
    layer = big[::2, :, 0].T.T                    # strided layer
    transposed = np.transpose(rng.random((3, 5, 6)).astype(np.float32), (1, 2, 0))
    path = str(tmp_path / "strided.exr")
    write_exr(path, rgb, {"radius": layer})
    back, layers = read_exr(path)
    np.testing.assert_array_equal(back, rgb)
    np.testing.assert_array_equal(layers["radius"], layer)
    write_exr(path, transposed)
    np.testing.assert_array_equal(read_exr(path)[0], transposed)


def test_exr_write_leaves_no_temp_files_and_replaces(tmp_path):
    path = tmp_path / "a.exr"
    write_exr(str(path), np.zeros((2, 2, 3)))
    write_exr(str(path), np.ones((2, 2, 3)))
    assert os.listdir(tmp_path) == ["a.exr"]
    assert read_exr(str(path))[0].min() == 1.0


@pytest.mark.parametrize("rgb, layers, match", [
    (np.zeros((4, 4)), None, "H, W, 3"),
    (np.zeros((4, 4, 3)), {"radius": np.zeros((3, 4))}, "shape"),
    (np.zeros((4, 4, 3)), {"R": np.zeros((4, 4))}, "layer name"),
    (np.zeros((4, 4, 3)), {"a.b": np.zeros((4, 4))}, "layer name"),
])
def test_exr_write_rejects_bad_input(tmp_path, rgb, layers, match):
    path = str(tmp_path / "bad.exr")
    with pytest.raises(FilmError, match=match):
        write_exr(path, rgb, layers)
    assert os.listdir(tmp_path) == []


def test_exr_read_errors_name_the_file(tmp_path):
    missing = str(tmp_path / "missing.exr")
    with pytest.raises(FilmError, match="missing.exr: cannot read EXR"):
        read_exr(missing)
    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"not an image at all")
    with pytest.raises(FilmError, match="junk.exr: cannot read EXR: not an OpenEXR file"):
        read_exr(str(junk))
    truncated = tmp_path / "cut.exr"
    write_exr(str(truncated), np.ones((16, 16, 3)))
    truncated.write_bytes(truncated.read_bytes()[:40])
    with pytest.raises(FilmError, match="cut.exr") as info:
        read_exr(str(truncated))
    assert "\n" not in str(info.value)


def test_write_exr_into_missing_folder_fails_clearly(tmp_path):
    with pytest.raises(FilmError, match="nowhere"):
        write_exr(str(tmp_path / "nowhere" / "x.exr"), np.zeros((2, 2, 3)))


def test_png_decodes_to_the_tone_mapped_pixels(tmp_path):
    rgb = np.array([[[0.0, 0.5, 1.0], [0.0031308, 2.0, 0.18]],
                    [[np.nan, np.inf, -1.0], [0.25, 0.25, 0.25]]])
    path = str(tmp_path / "p.png")
    write_png(path, rgb)
    px = _decode_png(path)
    assert px.shape == (2, 2, 3)
    # sRGB OETF by hand: 0.5 -> 1.055 * 0.5^(1/2.4) - 0.055 = 0.7354 -> 188.
    np.testing.assert_array_equal(px[0, 0], [0, 188, 255])
    np.testing.assert_array_equal(px[0, 1], [10, 255, 118])   # 12.92*0.0031308*255 = 10.3
    np.testing.assert_array_equal(px[1, 0], [0, 255, 0])       # NaN black, Inf white, <0 black
    write_png(path, rgb, exposure=1.0)                          # one stop up: 0.25 -> 0.5
    np.testing.assert_array_equal(_decode_png(path)[1, 1], [188, 188, 188])


def test_png_rgb8_and_rgba_round_trip_and_matplotlib_agrees(tmp_path):
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (9, 13, 3), dtype=np.uint8)
    path = str(tmp_path / "u8.png")
    write_png_rgb8(path, img[:, ::-1])              # non-contiguous input
    np.testing.assert_array_equal(_decode_png(path), img[:, ::-1])
    rgba = rng.integers(0, 256, (3, 4, 4), dtype=np.uint8)
    write_png_rgb8(path, rgba)
    np.testing.assert_array_equal(_decode_png(path), rgba)
    mpl_image = pytest.importorskip("matplotlib.image")
    np.testing.assert_array_equal(np.round(mpl_image.imread(path) * 255).astype(np.uint8), rgba)


def test_png_rejects_wrong_dtype(tmp_path):
    with pytest.raises(FilmError, match="uint8"):
        write_png_rgb8(str(tmp_path / "x.png"), np.zeros((2, 2, 3), np.float32))


def test_tonemap_is_monotonic_and_clamped():
    x = np.linspace(-1, 3, 200)[:, None, None] * np.ones((1, 1, 3))
    u8 = tonemap_srgb8(x)[:, 0, 0].astype(int)
    assert u8[0] == 0 and u8[-1] == 255 and np.all(np.diff(u8) >= 0)
