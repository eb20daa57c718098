"""Photos read whole, reduced or by window: TIFF (JPEG-in-TIFF, striped or tiled, BigTIFF, 16-bit) through
GDAL block by block, JPEG through OpenCV; and a whole mosaic from TIFF frames."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio

from tests.scenes import make_flight, make_texture
from workers.image_meta import InvalidImageError, inspect_image
from workers.photo_io import WindowReader, read_reduced, reduced_size
from workers.pipeline import process_directory

WIDTH, HEIGHT = 3000, 200  # a strip frame's shape, reduced: the long side across track


def _write_tiff(path: Path, bgr: np.ndarray, **options: object) -> Path:
    bands = np.moveaxis(bgr[..., ::-1], 2, 0)
    profile = {"driver": "GTiff", "width": bgr.shape[1], "height": bgr.shape[0], "count": 3, "dtype": bands.dtype.name}
    with rasterio.open(path, "w", **{**profile, **options}) as dst:
        dst.write(bands)
    return path


@pytest.fixture(scope="module")
def frame() -> np.ndarray:
    return make_texture(HEIGHT, WIDTH, seed=2)  # (H, W, 3) uint8 BGR


@pytest.mark.parametrize(
    "options",
    [
        {"compress": "jpeg", "photometric": "ycbcr", "tiled": True, "blockxsize": 256, "blockysize": 256},
        {"compress": "jpeg", "photometric": "ycbcr", "tiled": False, "BIGTIFF": "YES"},
        {"compress": "deflate", "tiled": False},
    ],
    ids=["jpeg-tiled", "jpeg-striped-bigtiff", "deflate-striped"],
)
def test_tiff_windows_and_reduced_copies(tmp_path: Path, frame: np.ndarray, options: dict) -> None:
    path = _write_tiff(tmp_path / "f.tif", frame, **options)
    with rasterio.open(path) as src:
        whole = np.moveaxis(src.read()[::-1], 0, 2)  # what GDAL decodes, as BGR
    reader = WindowReader(path)
    assert reader.shape == (HEIGHT, WIDTH, 3)
    for rows, cols in ((slice(0, 37), slice(1000, 1511)), (slice(150, 200), slice(2900, 3000))):
        if options["compress"] != "jpeg":
            assert np.array_equal(reader[rows, cols], whole[rows, cols])
        else:  # libjpeg-turbo's decode (tests/unit/test_tiff_jpeg.py): the same brightness as GDAL's libjpeg 9,
            # whose colour differs on sharp colour edges (it interpolates the half-resolution chroma otherwise)
            diff = reader[rows, cols].astype(float) - whole[rows, cols]
            assert np.abs(diff @ [0.114, 0.587, 0.299]).mean() < 0.5 and np.abs(diff).mean() < 3
    reduced, size = read_reduced(path, 750)  # type: ignore[misc]
    assert size == (WIDTH, HEIGHT) and reduced.shape[:2][::-1] == reduced_size(WIDTH, HEIGHT, 750) == (750, 50)
    expected = cv2.resize(whole, (750, 50), interpolation=cv2.INTER_AREA).astype(int)
    assert np.abs(reduced.astype(int) - expected).mean() < 1.0  # an area average, as cv2.INTER_AREA's


def test_sixteen_bit_and_single_band_tiffs(tmp_path: Path, frame: np.ndarray) -> None:
    wide = frame.astype(np.uint16) * 256 + 100  # the top 8 bits are the 8-bit frame
    path = _write_tiff(tmp_path / "16.tif", wide, compress="deflate")
    assert np.array_equal(WindowReader(path)[0:10, 0:20], frame[0:10, 0:20])
    gray = tmp_path / "gray.tif"
    with rasterio.open(gray, "w", driver="GTiff", width=40, height=30, count=1, dtype="uint8") as dst:
        dst.write(np.arange(1200, dtype=np.uint8).reshape(1, 30, 40))
    image, _ = read_reduced(gray, 100)  # type: ignore[misc]
    assert image.shape == (30, 40, 3) and np.array_equal(image[..., 0], image[..., 2])
    floats = tmp_path / "float.tif"
    with rasterio.open(floats, "w", driver="GTiff", width=40, height=30, count=3, dtype="float32") as dst:
        dst.write(np.zeros((3, 30, 40), np.float32))
    assert read_reduced(floats, 100) is None
    with pytest.raises(InvalidImageError):
        inspect_image(floats)
    assert inspect_image(path)["width"] == WIDTH  # 16-bit RGB, which Pillow cannot open: GDAL checks it


def test_upload_check_decodes_tiffs_block_by_block(tmp_path: Path, frame: np.ndarray) -> None:
    options = {"compress": "jpeg", "photometric": "ycbcr", "tiled": True, "blockxsize": 256, "blockysize": 256}
    path = _write_tiff(tmp_path / "good.tif", frame, **options)
    meta = inspect_image(path)
    assert (meta["width"], meta["height"], meta["format"]) == (WIDTH, HEIGHT, "TIFF")
    data = path.read_bytes()
    cut = tmp_path / "cut.tif"
    cut.write_bytes(data[: len(data) * 2 // 3])  # the last tiles' data is missing
    with pytest.raises(InvalidImageError, match="corrupt or truncated"):
        inspect_image(cut)


def test_a_mosaic_from_tiff_frames_matches_the_one_from_jpegs(tmp_path: Path) -> None:
    """The same frames as JPEGs and as (lossless) tiled TIFFs holding the JPEGs' pixels: both mosaics use every
    frame and agree, at the working and at the photos' own resolution (the TIFFs read by window)."""
    make_flight(tmp_path / "jpeg", n_frames=5, rotation_deg=8, gps=False, seed=9)
    (tmp_path / "tiff").mkdir()
    for jpeg in sorted((tmp_path / "jpeg").glob("*.jpg")):
        _write_tiff(tmp_path / "tiff" / f"{jpeg.stem}.tif", cv2.imread(str(jpeg)), compress="deflate", tiled=True)
    options = {"working_max_px": 320, "output_resolution": "native"}
    ours = {k: process_directory(tmp_path / k, tmp_path / f"out-{k}", options) for k in ("jpeg", "tiff")}
    assert len(ours["jpeg"]["frames_used"]) == len(ours["tiff"]["frames_used"]) == 5
    for side in ("width", "height"):
        assert abs(ours["jpeg"]["mosaic"][side] - ours["tiff"]["mosaic"][side]) <= 2
    with (
        rasterio.open(tmp_path / "out-jpeg" / "mosaic.tif") as a,
        rasterio.open(tmp_path / "out-tiff" / "mosaic.tif") as b,
    ):
        h, w = min(a.height, b.height), min(a.width, b.width)
        window = rasterio.windows.Window(0, 0, w, h)
        both = (a.read_masks(1, window=window) > 0) & (b.read_masks(1, window=window) > 0)
        inner = cv2.erode(both.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0
        diff = np.abs(a.read(window=window).astype(int) - b.read(window=window).astype(int))[:, inner]
    assert inner.mean() > 0.3 and diff.mean() < 2.0, diff.mean()
