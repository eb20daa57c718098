"""A JPEG-in-TIFF's blocks decoded by libjpeg-turbo (``workers.tiff_jpeg``): windows at full size against Pillow's
decode of the whole file (libtiff and the same libjpeg-turbo), reduced copies at a DCT scale against GDAL's full decode
area-averaged: tiled and striped, YCbCr- and RGB-coded, one band; what it leaves to GDAL; the block cache; and the
readers built on it (the working copies, the upload check, the previews) giving GDAL's figures."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import rasterio
from PIL import Image
from rasterio.windows import Window

import workers.image_meta as image_meta
import workers.photo_io as photo_io
from tests.scenes import make_texture
from workers.photo_check import DUPLICATE_BITS, hamming, preview_jpeg
from workers.tiff_jpeg import BlockCache, JpegBlockError, JpegBlocks

WIDTH, HEIGHT = 2048, 328  # a reduced strip frame: the edge tiles are partial, 328 = 8 x 41 rows
TILED = {"compress": "jpeg", "jpeg_quality": 90, "tiled": True, "blockxsize": 256, "blockysize": 256}  # as the strips


LUMA = np.array([0.299, 0.587, 0.114])


def _write(path: Path, rgb: np.ndarray, **options: object) -> Path:
    bands = np.moveaxis(rgb, 2, 0) if rgb.ndim == 3 else rgb[None]
    profile = {"driver": "GTiff", "width": rgb.shape[1], "height": rgb.shape[0], "count": len(bands), "dtype": "uint8"}
    with rasterio.open(path, "w", **{**profile, **options}) as dst:
        dst.write(bands)
    return path


def _gdal(path: Path) -> np.ndarray:
    """GDAL's full decode, (h, w, bands)."""
    with rasterio.open(path) as src:
        return np.moveaxis(src.read(), 0, 2)


def _box(image: np.ndarray, s: int) -> np.ndarray:
    h, w = image.shape[0] // s, image.shape[1] // s
    return image[: h * s, : w * s].reshape(h, s, w, s, -1).astype(float).mean(axis=(1, 3))


@pytest.fixture(scope="module")
def rgb() -> np.ndarray:
    return np.ascontiguousarray(make_texture(HEIGHT, WIDTH, seed=5)[..., ::-1])  # RGB


@pytest.mark.parametrize(
    "options",
    [
        {**TILED, "photometric": "ycbcr"},
        {**TILED, "photometric": "rgb"},
        {
            "compress": "jpeg",
            "jpeg_quality": 90,
            "photometric": "ycbcr",
            "tiled": False,
            "BIGTIFF": "YES",
        },  # strips of 8 or 16 rows
        {**TILED, "grey": True},
    ],
    ids=["tiled-ycbcr", "tiled-rgb", "striped-ycbcr-bigtiff", "tiled-grey"],
)
def test_scaled_blocks_are_the_area_average_of_gdals_decode(tmp_path: Path, rgb: np.ndarray, options: dict) -> None:
    options = dict(options)
    image = rgb[..., 1] if options.pop("grey", False) else rgb
    path = _write(tmp_path / "f.tif", image, **options)
    jpeg = JpegBlocks.open(path)
    assert jpeg is not None and (jpeg.width, jpeg.height, jpeg.bands) == (
        WIDTH,
        HEIGHT,
        image.ndim if image.ndim == 3 else 1,
    )
    whole = _gdal(path)
    for s in (2, 4, 8):
        reduced = jpeg.reduced(s)
        assert reduced.shape[:2] == (HEIGHT // s, WIDTH // s)
        box = _box(whole, s)
        reduced = reduced.reshape(box.shape).astype(float)
        # brightness: the same pixels' means to within the transform's rounding (the DC's quantisation at 1/8)
        luma = np.abs((reduced - box) @ LUMA[: box.shape[2]] / LUMA[: box.shape[2]].sum())
        assert luma.mean() < 0.4 and luma.max() <= 6, (s, luma.mean(), luma.max())
        # colour: libjpeg interpolates the YCbCr half-resolution colour planes where GDAL's decode was averaged,
        # so a few px on sharp colour edges differ
        colour = np.abs(reduced - box)
        assert colour.mean() < 1.2 and np.percentile(colour, 99) <= 8 and colour.max() <= 40, (s, colour.max())
    assert jpeg.scale_for(7.9) == 4 and jpeg.scale_for(1.9) == 1


@pytest.mark.parametrize(
    "options",
    [
        {**TILED, "photometric": "ycbcr"},
        {**TILED, "photometric": "rgb"},
        {"compress": "jpeg", "jpeg_quality": 90, "photometric": "ycbcr", "tiled": False},  # strips of 8 or 16 rows
        {**TILED, "grey": True},
        {**TILED, "photometric": "ycbcr", "JPEGTABLESMODE": 0},  # every block its own tables
    ],
    ids=["tiled-ycbcr", "tiled-rgb", "striped-ycbcr", "tiled-grey", "tiled-no-shared-tables"],
)
def test_windows_are_the_whole_decode_cut(tmp_path: Path, rgb: np.ndarray, options: dict) -> None:
    """Windows across block edges, at the image's edges and over all of it, read through the cache, equal the
    same libjpeg-turbo's decode of the whole file to the bit (Pillow reads JPEG-in-TIFF through libtiff), in
    ``WindowReader``'s BGR too."""
    options = dict(options)
    grey = options.pop("grey", False)
    path = _write(tmp_path / "f.tif", rgb[..., 1] if grey else rgb, **options)
    with Image.open(path) as img:
        whole = np.asarray(img)
    jpeg = JpegBlocks.open(path)
    assert jpeg is not None
    cache = BlockCache(40 * 256 * 256 * 3)  # 40 tiles: blocks are dropped and decoded again on the way
    reader = photo_io.WindowReader(path)
    windows = [
        (0, 37, 1000, 1511),
        (250, 328, 1990, 2048),
        (0, HEIGHT, 0, WIDTH),
        (255, 257, 0, WIDTH),
        (17, 300, 3, 5),
    ]
    opencv = JpegBlocks.open(path, photo_io.decode_bgr)  # BGR blocks, in the same cache as Pillow's RGB ones
    assert opencv is not None
    for r0, r1, c0, c1 in windows * 2:
        assert np.array_equal(jpeg.window(r0, r1, c0, c1, cache), whole[r0:r1, c0:c1])
        assert np.array_equal(
            opencv.window(r0, r1, c0, c1, cache), whole[r0:r1, c0:c1, ::-1] if not grey else whole[r0:r1, c0:c1]
        )
        bgr = whole[r0:r1, c0:c1, ::-1] if not grey else np.repeat(whole[r0:r1, c0:c1, None], 3, axis=2)
        assert np.array_equal(reader[r0:r1, c0:c1], bgr)
    assert 0 < cache.bytes <= cache.max_bytes
    assert jpeg.window(5, 5, 0, 10, cache).shape[:2] == (0, 10)


def test_what_it_leaves_to_gdal(tmp_path: Path, rgb: np.ndarray) -> None:
    assert JpegBlocks.open(_write(tmp_path / "deflate.tif", rgb, compress="deflate")) is None
    wide = rgb.astype(np.uint16) * 257
    with rasterio.open(
        tmp_path / "16.tif", "w", driver="GTiff", width=WIDTH, height=HEIGHT, count=3, dtype="uint16"
    ) as dst:
        dst.write(np.moveaxis(wide, 2, 0))
    assert JpegBlocks.open(tmp_path / "16.tif") is None
    banded = _write(tmp_path / "band.tif", rgb, **TILED, interleave="band")  # a JPEG stream per band
    assert JpegBlocks.open(banded) is None
    assert JpegBlocks.open(tmp_path / "missing.tif") is None
    odd = _write(tmp_path / "odd.tif", rgb[:, :2044], **TILED, photometric="ycbcr")
    jpeg = JpegBlocks.open(odd)
    assert jpeg is not None and jpeg.scale_for(8) == 4  # 2044 = 4 x 511: no 8 x 8 pixel is whole at its edge
    with pytest.raises(ValueError):
        jpeg.reduced(8)


def test_a_window_over_blocks_never_written_is_gdals(tmp_path: Path, rgb: np.ndarray) -> None:
    """A sparse TIFF (blocks with no data left out, offset 0): such a window is read by GDAL, zeros where nothing was
    written, the written block the same picture."""
    path = tmp_path / "sparse.tif"
    profile = {"driver": "GTiff", "width": 1024, "height": 512, "count": 3, "dtype": "uint8", "sparse_ok": True}
    with rasterio.open(path, "w", **profile, **TILED, photometric="ycbcr") as dst:
        dst.write(np.moveaxis(rgb[:256, :512], 2, 0), window=Window(0, 0, 512, 256))
    jpeg = JpegBlocks.open(path)
    assert jpeg is not None and jpeg.window(0, 256, 0, 512).shape == (256, 512, 3)  # the block written
    with pytest.raises(JpegBlockError, match="not stored"):
        jpeg.window(0, 512, 0, 1024)
    window = photo_io.WindowReader(path)[0:512, 0:1024]
    assert not window[256:].any() and not window[:, 512:].any()
    diff = np.abs(window[:256, :512].astype(int) - rgb[:256, :512, ::-1])
    assert diff.mean() < 6  # JPEG at quality 90 of a busy texture


def test_a_cut_file_is_left_to_gdal(tmp_path: Path, rgb: np.ndarray) -> None:
    path = _write(tmp_path / "f.tif", rgb, **TILED, photometric="ycbcr")
    data = path.read_bytes()
    cut = tmp_path / "cut.tif"
    cut.write_bytes(data[: len(data) * 2 // 3])
    jpeg = JpegBlocks.open(cut)
    assert jpeg is not None
    with pytest.raises(JpegBlockError, match="cut short"):
        jpeg.reduced(8)
    assert photo_io.read_reduced(cut, WIDTH // 8) is None  # GDAL fails it too
    with pytest.raises(image_meta.InvalidImageError, match="corrupt or truncated"):
        image_meta.inspect_image(cut)


def test_the_readers_built_on_it_give_gdals_figures(tmp_path: Path, rgb: np.ndarray, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Working copy, upload check and preview of a JPEG-in-TIFF through the scaled decode, then through GDAL alone."""
    big = np.tile(rgb[:320], (2, 4, 1))  # 8192 x 640: the upload check's cells are 16 px, two 8 x 8 blocks
    path = _write(tmp_path / "f.tif", big, **TILED, photometric="ycbcr")
    fast = photo_io.read_reduced(path, 1024), image_meta.inspect_image(path)["quality"], preview_jpeg(path, 256)
    monkeypatch.setattr(photo_io, "read_jpeg_reduced", lambda *_: None)
    monkeypatch.setattr(image_meta, "_scaled_block_means", lambda _: None)
    monkeypatch.setattr(JpegBlocks, "open", classmethod(lambda cls, _: None))
    slow = photo_io.read_reduced(path, 1024), image_meta.inspect_image(path)["quality"], preview_jpeg(path, 256)
    (copy, size), (copy_gdal, size_gdal) = fast[0], slow[0]  # type: ignore[misc]
    assert size == size_gdal == (8192, 640) and copy.shape == copy_gdal.shape == (80, 1024, 3)
    diff = np.abs(copy.astype(int) - copy_gdal)  # BGR, as GDAL's, area-averaged (colour planes interpolated)
    assert diff.mean() < 1.0 and np.percentile(diff, 99) <= 6
    quality, quality_gdal = fast[1], slow[1]
    assert quality["analysed_px"] == quality_gdal["analysed_px"] == [512, 40]
    assert abs(quality["mean_brightness"] - quality_gdal["mean_brightness"]) < 0.3
    assert abs(quality["sharpness"] / quality_gdal["sharpness"] - 1) < 0.02
    assert hamming(quality["phash"], quality_gdal["phash"]) < DUPLICATE_BITS  # the same picture, by its own test
    with Image.open(io.BytesIO(fast[2])) as a, Image.open(io.BytesIO(slow[2])) as b:
        assert a.size == b.size == (256, 20)
        assert np.abs(np.asarray(a).astype(int) - np.asarray(b)).mean() < 3  # both re-encoded as JPEG
