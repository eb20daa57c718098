"""The mosaic's COGs: overviews averaged under the mask by our own pyramid (fed band by band), copied with the
full-resolution pixels by GDAL's COG driver; checked against a float64 oracle and read back with rasterio."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.windows import Window
from rio_cogeo.cogeo import cog_validate

from workers.raster_io import (
    OverviewPyramid,
    masked_half,
    open_block_writer,
    open_index_writer,
    translate_index_to_cog,
    translate_to_cog,
)


def mean_under_mask(rgb: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The oracle: each 2 x 2 cell's mean over its pixels with data, rounded half up, in float64."""
    height, width = mask.shape
    pad = ((0, height % 2), (0, width % 2))
    m = np.pad(mask, pad).astype(np.float64)
    v = np.pad(rgb, (*pad, (0, 0))).astype(np.float64) * m[..., None]
    total = v[0::2, 0::2] + v[1::2, 0::2] + v[0::2, 1::2] + v[1::2, 1::2]
    count = m[0::2, 0::2] + m[1::2, 0::2] + m[0::2, 1::2] + m[1::2, 1::2]
    mean = np.floor(total / np.maximum(count, 1)[..., None] + 0.5)
    return np.where(count[..., None] > 0, mean, 0).astype(np.uint8), count > 0


def scene(height: int, width: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random pixels under a mask with whole empty regions, a ragged edge and isolated holes."""
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    yy, xx = np.mgrid[0:height, 0:width]
    mask = (xx + 0.7 * yy < 0.9 * width) & (rng.random((height, width)) > 0.1)
    return rgb, mask


@pytest.mark.parametrize(("height", "width"), [(64, 48), (37, 51), (3, 29)])
def test_masked_half_is_the_mean_of_the_pixels_with_data(height: int, width: int) -> None:
    rgb, mask = scene(height, width, seed=height)
    half, covered = masked_half(rgb, mask)
    expected, expected_covered = mean_under_mask(rgb, mask)
    assert half.shape == expected.shape
    np.testing.assert_array_equal(covered, expected_covered)
    np.testing.assert_array_equal(half, expected)
    assert covered.any() and not covered.all()


def test_pyramid_fed_in_odd_bands_equals_halving_the_whole(tmp_path: Path) -> None:
    height, width = 203, 150  # bands of 37 rows: every level gets odd chunks, carried over
    rgb, mask = scene(height, width, seed=3)
    paths = [tmp_path / f"level_{n}.tif" for n in range(3)]
    with OverviewPyramid(paths, width, height) as pyramid:
        for y in range(0, height, 37):
            pyramid.add(rgb[y : y + 37], mask[y : y + 37])
    level_rgb, level_mask = rgb, mask
    for path in paths:
        level_rgb, level_mask = mean_under_mask(level_rgb, level_mask)
        with rasterio.open(path) as level:
            np.testing.assert_array_equal(np.moveaxis(level.read(), 0, 2), level_rgb)
            np.testing.assert_array_equal(level.read_masks(1) > 0, level_mask)


def test_index_pyramid_takes_frame_numbers_as_they_are(tmp_path: Path) -> None:
    index = np.random.default_rng(4).integers(0, 5, (99, 70)).astype(np.uint16)
    paths = [tmp_path / "level_0.tif", tmp_path / "level_1.tif"]
    with OverviewPyramid(paths, 70, 99, index=True) as pyramid:
        for y in range(0, 99, 25):
            pyramid.add(index[y : y + 25])
    with rasterio.open(paths[0]) as first, rasterio.open(paths[1]) as second:
        np.testing.assert_array_equal(first.read(1), index[::2, ::2])
        np.testing.assert_array_equal(second.read(1), index[::4, ::4])


def write_scratch(
    path: Path, rgb: np.ndarray, mask: np.ndarray, crs: int | None, transform: list[float] | None
) -> None:
    height, width = mask.shape
    with open_block_writer(path, width, height, crs, transform, compress=None) as write:
        for y in range(0, height, 300):
            rows = min(300, height - y)
            write(Window(0, y, width, rows), rgb[y : y + rows], mask[y : y + rows])


@pytest.mark.parametrize("compression", ["deflate", "zstd"])
def test_cog_keeps_every_pixel_and_averages_its_overviews_under_the_mask(tmp_path: Path, compression: str) -> None:
    height, width = 1100, 1700  # overviews 2 and 4; the top-right tiles have no data at all
    rgb, mask = scene(height, width, seed=5)
    mask[:, 1300:] = False
    rgb[~mask] = 0
    transform = [0.5, 0.0, 500_000.0, 0.0, -0.5, 5_600_000.0]
    write_scratch(tmp_path / "scratch.tif", rgb, mask, 32630, transform)
    cog = tmp_path / "mosaic.tif"
    translate_to_cog(tmp_path / "scratch.tif", cog, compression, tags={"TIFFTAG_IMAGEDESCRIPTION": "a <test> & mosaic"})

    valid, errors, _ = cog_validate(str(cog))
    assert valid, errors
    assert not (tmp_path / "scratch.tif.levels").exists()  # the overview levels are removed
    with rasterio.open(cog) as src:
        assert src.crs.to_epsg() == 32630 and list(src.transform)[:6] == transform
        assert src.tags()["TIFFTAG_IMAGEDESCRIPTION"] == "a <test> & mosaic"
        assert src.tags()["TIFFTAG_SOFTWARE"].startswith("Fotoskhema")
        assert src.overviews(1) == [2, 4]
        np.testing.assert_array_equal(np.moveaxis(src.read(), 0, 2), rgb)
        np.testing.assert_array_equal(src.dataset_mask() > 0, mask)
        empty = src.block_window(1, 0, 3)  # a tile with no data: not stored, read as masked zeros
        assert src.get_tag_item("BLOCK_OFFSET_3_0", "TIFF", bidx=1) is None
        assert not src.read(window=empty).any() and not src.dataset_mask(window=empty).any()
    level_rgb, level_mask = rgb, mask
    for n in range(2):
        level_rgb, level_mask = mean_under_mask(level_rgb, level_mask)
        with rasterio.open(cog, overview_level=n) as level:
            np.testing.assert_array_equal(np.moveaxis(level.read(), 0, 2), level_rgb)
            np.testing.assert_array_equal(level.dataset_mask() > 0, level_mask)


def test_cog_of_pixels_placed_nowhere_stays_unplaced(tmp_path: Path) -> None:
    rgb, mask = scene(600, 700, seed=6)
    write_scratch(tmp_path / "scratch.tif", rgb, mask, None, None)
    translate_to_cog(tmp_path / "scratch.tif", tmp_path / "view.tif", "lzw")
    with rasterio.open(tmp_path / "view.tif") as src:
        assert src.crs is None and src.transform.is_identity
        np.testing.assert_array_equal(np.moveaxis(src.read(), 0, 2), rgb)


def test_frame_index_cog_is_nodata_zero_with_nearest_overviews(tmp_path: Path) -> None:
    height, width = 900, 1300
    index = np.zeros((height, width), np.uint16)
    index[:, :600], index[:, 600:1000] = 1, 2  # right of 1000: no frame
    transform = [0.5, 0.0, 500_000.0, 0.0, -0.5, 5_600_000.0]
    with open_index_writer(tmp_path / "index.tmp.tif", width, height, 32630, transform, compress=None) as write:
        write(Window(0, 0, width, height), index)
    cog = tmp_path / "frame_index.tif"
    translate_index_to_cog(tmp_path / "index.tmp.tif", cog, "jpeg", tags={"FRAME_1": "a.jpg", "FRAME_2": "b & c.jpg"})
    valid, errors, _ = cog_validate(str(cog))
    assert valid, errors
    with rasterio.open(cog) as src:
        assert src.nodata == 0 and src.compression.name == "deflate"  # never JPEG
        assert src.tags()["FRAME_2"] == "b & c.jpg"
        np.testing.assert_array_equal(src.read(1), index)
        assert src.crs.to_epsg() == 32630
    with rasterio.open(cog, overview_level=0) as level:
        np.testing.assert_array_equal(level.read(1), index[::2, ::2])
