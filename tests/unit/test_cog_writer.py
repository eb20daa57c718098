"""A mosaic's COG assembled from its bands (workers/cog_writer.py), against GDAL's COG driver writing the same
raster (raster_io.translate_to_cog, the crack reports' path) as the oracle."""

from __future__ import annotations

import errno
import os
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rasterio
from rasterio.windows import Window
from rio_cogeo.cogeo import cog_validate
from rio_tiler.constants import WGS84_CRS
from rio_tiler.io import Reader

from tests.scenes import make_flight
from workers import cog_writer
from workers.cog_writer import (
    first_level_path,
    open_cog_band_writer,
    open_cog_index_band_writer,
    write_cog_from_bands,
)
from workers.pipeline import process_directory, run_stage
from workers.raster_io import open_block_writer, open_index_writer, translate_index_to_cog, translate_to_cog
from workers.stages import compose_mosaic
from workers.workspace import JobWorkspace

TRANSFORM = [0.5, 0.0, 500000.0, 0.0, -0.5, 6000000.0]  # 0.5 m px in UTM 33N
EPSG = 32633


def scene(width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A smooth textured picture (h, w, 3) uint8, an elliptical coverage mask and a frame index of blocks."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    rgb = np.stack(
        [(xx * 0.2 + yy * 0.1) % 256, 128 + 90 * np.sin(xx / 37) * np.cos(yy / 23), (xx * yy / 900) % 200 + 30],
        axis=-1,
    ).astype(np.uint8)
    mask = ((xx - width / 2) / (0.48 * width)) ** 2 + ((yy - height / 2) / (0.45 * height)) ** 2 < 1
    index = (((xx // 97) + 13 * (yy // 61)) % 40 + 1).astype(np.uint16) * mask
    return rgb, mask, index


def write_bands(
    folder: Path, rgb: np.ndarray, mask: np.ndarray, index: np.ndarray, codec: str, kept: bool = False
) -> tuple[list[Path], list[Path]]:
    """The raster as 512-row bands, as compose_mosaic's parts write them, 256 px windows at a time; ``kept``: each
    with its first overview level beside it (``first_level_path``), as a small mosaic's are."""
    height, width = mask.shape
    bands, indexes = [], []
    for y in range(0, height, 512):
        h = min(512, height - y)
        band, band_index = folder / f"band_{y}.tif", folder / f"index_{y}.tif"
        levels = (first_level_path(band), first_level_path(band_index)) if kept else (None, None)
        with (
            open_cog_band_writer(band, width, h, codec, levels[0]) as write,
            open_cog_index_band_writer(band_index, width, h, codec, levels[1]) as write_index,
        ):
            for dy in range(0, h, 256):
                for x in range(0, width, 256):
                    w, hh = min(256, width - x), min(256, h - dy)
                    rows, cols = slice(y + dy, y + dy + hh), slice(x, x + w)
                    write(Window(x, dy, w, hh), rgb[rows, cols], mask[rows, cols])
                    write_index(Window(x, dy, w, hh), index[rows, cols])
        bands.append(band)
        indexes.append(band_index)
    return bands, indexes


def gdal_cogs(folder: Path, rgb: np.ndarray, mask: np.ndarray, index: np.ndarray, codec: str) -> tuple[Path, Path]:
    """The oracle: the same raster through a scratch GeoTIFF and GDAL's COG driver."""
    height, width = mask.shape
    with open_block_writer(folder / "scratch.tif", width, height, EPSG, TRANSFORM, compress=None) as write:
        write(Window(0, 0, width, height), rgb, mask)
    translate_to_cog(folder / "scratch.tif", folder / "gdal.tif", codec, tags={"TIFFTAG_IMAGEDESCRIPTION": "m"})
    with open_index_writer(folder / "scratch_index.tif", width, height, EPSG, TRANSFORM, compress=None) as write_index:
        write_index(Window(0, 0, width, height), index)
    tags = {"TIFFTAG_IMAGEDESCRIPTION": "i", "FRAME_1": "a.tif"}
    translate_index_to_cog(folder / "scratch_index.tif", folder / "gdal_index.tif", codec, tags=tags)
    return folder / "gdal.tif", folder / "gdal_index.tif"


def assemble(
    folder: Path, bands: list[Path], indexes: list[Path], size: tuple[int, int], codec: str, bigtiff: bool | None = None
) -> tuple[Path, Path]:
    """Both COGs from their bands, placed and tagged as :func:`gdal_cogs` places and tags them."""
    write = partial(
        write_cog_from_bands, width=size[0], height=size[1], crs=EPSG, transform=TRANSFORM, compression=codec
    )
    tags = {"TIFFTAG_IMAGEDESCRIPTION": "m"}
    write(folder / "ours.tif", bands, kind="rgb", tags=tags, scratch=folder / "m.tmp.tif", bigtiff=bigtiff)
    tags = {"TIFFTAG_IMAGEDESCRIPTION": "i", "FRAME_1": "a.tif"}
    write(folder / "ours_index.tif", indexes, kind="index", tags=tags, scratch=folder / "i.tmp.tif")
    return folder / "ours.tif", folder / "ours_index.tif"


def overview(path: Path, factor: int) -> np.ma.MaskedArray:
    with rasterio.open(path) as src:
        shape = (src.count, -(-src.height // factor), -(-src.width // factor))
        return src.read(out_shape=shape, masked=True)


def same_file_but_pixels(ours: Path, theirs: Path) -> None:
    """Valid COGs with the same placement, tags (but the time written), layout, codec and overview factors."""
    valid, errors, warnings = cog_validate(ours, quiet=True)
    assert valid and not errors and not warnings, (errors, warnings)
    with rasterio.open(ours) as a, rasterio.open(theirs) as b:
        assert (a.width, a.height, a.count, a.dtypes, a.nodata) == (b.width, b.height, b.count, b.dtypes, b.nodata)
        assert a.crs == b.crs and a.transform == b.transform and a.block_shapes == b.block_shapes
        assert a.overviews(1) == b.overviews(1) and a.overviews(1)
        assert a.mask_flag_enums == b.mask_flag_enums
        assert a.tags(ns="IMAGE_STRUCTURE") == b.tags(ns="IMAGE_STRUCTURE")  # LAYOUT=COG, codec, predictor
        ours_tags, their_tags = a.tags(), b.tags()
        assert ours_tags.pop("TIFFTAG_DATETIME") and their_tags.pop("TIFFTAG_DATETIME")
        assert ours_tags == their_tags


def block_mean(rgb: np.ndarray, mask: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """The oracle of an overview level: over each ``factor`` x ``factor`` block (the last ones cut by the edge),
    the mean of the covered pixels rounded half up, and whether any is covered (float-free, int64)."""
    h, w = mask.shape
    rows, cols = -(-h // factor), -(-w // factor)
    covered = np.zeros((rows * factor, cols * factor), np.int64)
    covered[:h, :w] = mask
    values = np.zeros((rows * factor, cols * factor, 3), np.int64)
    values[:h, :w] = rgb * mask[..., None]
    count = covered.reshape(rows, factor, cols, factor).sum(axis=(1, 3))
    total = values.reshape(rows, factor, cols, factor, 3).sum(axis=(1, 3))
    return (2 * total + count[..., None]) // (2 * np.maximum(count, 1)[..., None]), count > 0


@pytest.mark.parametrize(
    ("codec", "size", "bigtiff", "kept"),
    [
        ("deflate", (1300, 1100), None, False),
        ("deflate", (1301, 1099), None, True),
        ("jpeg", (1111, 1027), True, False),
    ],
)
def test_a_cog_from_bands_has_gdals_pixels_mask_and_tags(
    tmp_path: Path, codec: str, size: tuple[int, int], bigtiff: bool | None, kept: bool
) -> None:
    """The full resolution, its mask and the frame index are those of GDAL's COG driver to the pixel (JPEG too:
    the same tiles coded the same way); each overview is the mean of the covered pixels of its block of the full
    resolution (JPEG: as near it as the COG driver's), close to the COG driver's, and the frame index's top-left
    pixel, also from the first levels the band writers kept (an odd width and height there); the bands and their
    kept levels are gone and no scratch is left."""
    width, height = size
    rgb, mask, index = scene(width, height)
    gdal, gdal_index = gdal_cogs(tmp_path, rgb, mask, index, codec)
    bands, indexes = write_bands(tmp_path, rgb, mask, index, codec, kept)
    assert all(first_level_path(band).exists() == kept for band in bands + indexes)
    ours, ours_index = assemble(tmp_path, bands, indexes, size, codec, bigtiff=bigtiff)
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(("band", "index", "m.", "i.", ".o"))) == []
    same_file_but_pixels(ours, gdal)
    same_file_but_pixels(ours_index, gdal_index)
    assert (ours.read_bytes()[2] == 43) == bool(bigtiff)  # BigTIFF when asked (or past 4 GiB), else classic
    with rasterio.open(ours) as a, rasterio.open(gdal) as b:
        mine, theirs = a.read(masked=True), b.read(masked=True)
        np.testing.assert_array_equal(mine.mask, theirs.mask)
        np.testing.assert_array_equal(mine.filled(0), theirs.filled(0))
        factors = a.overviews(1)
    np.testing.assert_array_equal(rasterio.open(ours_index).read(1), rasterio.open(gdal_index).read(1))
    for factor in factors:
        level = overview(ours, factor)
        expected, covered = block_mean(rgb, mask, factor)
        np.testing.assert_array_equal(~np.ma.getmaskarray(level)[0], covered)
        error = np.abs(np.moveaxis(level.data, 0, 2).astype(np.int64) - expected)[covered]
        theirs = overview(gdal, factor)
        if codec == "jpeg":  # both lossy: as close to the exact mean as the COG driver's (2-4 grey levels here)
            coded = covered & ~np.ma.getmaskarray(theirs)[0]
            their_error = np.abs(np.moveaxis(theirs.data, 0, 2).astype(np.int64) - expected)[coded]
            assert error.mean() < 1.1 * their_error.mean(), (factor, error.mean(), their_error.mean())
        else:
            assert error.max() == 0, factor
        both = ~level.mask & ~theirs.mask
        assert (level.mask != theirs.mask).mean() < 0.01, factor
        assert np.abs(level.data.astype(np.int16) - theirs.data)[both].mean() < 3.0, factor
        np.testing.assert_array_equal(overview(ours_index, factor).data[0], index[::factor, ::factor])


def test_the_overviews_take_a_bands_kept_first_level_and_decode_one_that_does_not_fit(tmp_path: Path) -> None:
    """A band's kept first level is what the overviews are made from: a 2x2 sum raised there by 4 shows as +1 in the
    COG's first overview and nowhere else. One of another size, or cut short, is passed over and its band decoded.
    None is left."""
    width, height = 700, 1100  # three bands
    rgb, mask, index = scene(width, height)
    bands, indexes = write_bands(tmp_path, rgb, mask, index, "deflate", kept=True)
    kept = first_level_path(bands[0])
    with np.load(kept) as data:
        arrays = {name: data[name] for name in data.files}
    whole = (arrays["counts"] == 4) & (arrays["sums"].max(axis=2) < 4 * 250)
    r, c = (int(v[0]) for v in np.nonzero(whole))
    arrays["sums"][r, c] += 4
    np.savez(kept, **arrays)
    np.savez(
        first_level_path(bands[1]),
        rows=np.array(512),
        sums=np.zeros((4, 4, 3), np.uint16),
        counts=np.zeros((4, 4), np.uint16),
    )
    first_level_path(indexes[2]).write_bytes(b"PK\x03\x04 cut short")
    ours, ours_index = assemble(tmp_path, bands, indexes, (width, height), "deflate")
    assert not list(tmp_path.glob("*.level1.npz"))
    expected, covered = block_mean(rgb, mask, 2)
    level = overview(ours, 2)
    np.testing.assert_array_equal(~np.ma.getmaskarray(level)[0], covered)
    changed = np.moveaxis(level.data, 0, 2).astype(np.int64) - expected
    assert (changed[r, c] == 1).all()
    changed[r, c] = 0
    assert not changed[covered].any()
    np.testing.assert_array_equal(overview(ours_index, 2).data[0], index[::2, ::2])


def test_a_first_level_is_kept_only_from_windows_at_even_offsets(tmp_path: Path) -> None:
    """Pooled 2x2 blocks must not straddle two windows: a window at an odd offset is refused."""
    band = tmp_path / "band.tif"
    with open_cog_band_writer(band, 64, 64, "deflate", first_level_path(band)) as write:
        write(Window(0, 0, 8, 8), np.zeros((8, 8, 3), np.uint8), np.ones((8, 8), bool))
        with pytest.raises(ValueError, match="even offsets"):
            write(Window(9, 0, 8, 8), np.zeros((8, 8, 3), np.uint8), np.ones((8, 8), bool))


def test_rio_tiler_reads_the_same_tiles_from_its_overviews(tmp_path: Path) -> None:
    """A web map's tiles at a zoom that reads the overviews (the whole raster in one 256 px tile) and at one
    that reads the full resolution, from the assembled COG and from GDAL's."""
    rgb, mask, index = scene(1536, 1300)
    gdal, _ = gdal_cogs(tmp_path, rgb, mask, index, "deflate")
    ours, _ = assemble(tmp_path, *write_bands(tmp_path, rgb, mask, index, "deflate"), (1536, 1300), "deflate")
    with Reader(str(ours)) as a, Reader(str(gdal)) as b:
        assert a.info().overviews == b.info().overviews
        west, south, east, north = a.get_geographic_bounds(WGS84_CRS)
        assert a.minzoom < a.maxzoom
        for zoom in (a.minzoom, a.maxzoom):  # the coarsest overview, the full resolution
            tile = a.tms.tile((west + east) / 2, (south + north) / 2, zoom)
            mine, theirs = a.tile(tile.x, tile.y, zoom), b.tile(tile.x, tile.y, zoom)
            np.testing.assert_array_equal(mine.mask, theirs.mask)
            assert np.abs(mine.data.astype(np.int16) - theirs.data).mean() < 1.0, zoom


def read_outputs(ws: JobWorkspace) -> dict[str, Any]:
    with rasterio.open(ws.mosaic_path()) as src, rasterio.open(ws.frame_index_path()) as index:
        factor = src.overviews(1)[0]
        return {"mosaic": src.read(masked=True), "index": index.read(1), "overview": overview(ws.mosaic_path(), factor)}


def every_level(ws: JobWorkspace) -> list[np.ndarray]:
    """Both COGs' pixels and masks at full resolution and every overview level."""
    arrays = []
    for path in (ws.mosaic_path(), ws.frame_index_path()):
        with rasterio.open(path) as src:
            factors = src.overviews(1)
        for level in [None, *range(len(factors))]:
            with rasterio.open(path, overview_level=level) as src:
                arrays += [src.read(), src.read_masks()]
    return arrays


def same_outputs(ws: JobWorkspace, before: dict[str, Any]) -> None:
    """The same full resolution, mask and frame index as ``before``, overviews close to it, valid COGs, and
    neither band nor scratch nor half-written file left."""
    after = read_outputs(ws)
    np.testing.assert_array_equal(after["mosaic"].mask, before["mosaic"].mask)
    np.testing.assert_array_equal(after["mosaic"].filled(0), before["mosaic"].filled(0))
    np.testing.assert_array_equal(after["index"], before["index"])
    # across an odd height (1209 px here) GDAL averages windows of H / ceil(H / 2) = 1.998 px, weighing the
    # pixels they cut; the 2x2 blocks drift a row from them: 3 grey levels apart on this busy texture
    both = ~after["overview"].mask & ~before["overview"].mask
    assert np.abs(after["overview"].data.astype(np.int16) - before["overview"].data)[both].mean() < 4.0
    assert cog_validate(ws.mosaic_path(), quiet=True)[:2] == (True, [])
    assert cog_validate(ws.frame_index_path(), quiet=True)[:2] == (True, [])
    left = [p.name for p in ws.root.rglob("*.tif") if "tmp" in p.name or p.name.startswith((".", "band_", "index_"))]
    assert not left, left


def test_a_mosaic_is_composed_into_cogs_from_its_bands_and_a_stopped_finish_writes_the_same(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """compose_mosaic: bands of 512 rows (block_px 256 rounded up to the COG's tiles) written as the COG's tiles
    and assembled into the mosaic and frame index, with no scratch mosaic; composed again, the same COGs.
    Stopped midway (a band copied into the COG and deleted), with a band an older version wrote as ZSTD and a
    killed process's half-written COG beside it, the finish composes those bands again and writes the same
    COGs. The overviews come from the first levels the parts kept beside the bands, or from the bands decoded
    again (a large mosaic's, and the bands whose kept levels a stopped finish used up), the same either way."""
    make_flight(tmp_path / "frames", n_frames=6, frame_size=(640, 640), layout="grid", seed=5)
    process_directory(tmp_path / "frames", tmp_path / "job", {"working_max_px": 640, "block_px": 256})
    ws = JobWorkspace(tmp_path / "job")
    before = read_outputs(ws)
    assert before["mosaic"].shape[1] > 1024  # three bands or more
    ws.forget_stage_report("compose_mosaic")
    for record in (ws.root / "parts" / "compose_mosaic").glob("part_*.json"):
        record.unlink()
    kept, take = list[bool](), cog_writer._kept_first_level

    def taken(*args: Any) -> Any:  # whether each band's overviews came from the first level kept beside it
        level = take(*args)
        kept.append(level is not None)
        return level

    monkeypatch.setattr(cog_writer, "_kept_first_level", taken)
    run_stage(ws, "mosaic", "compose_mosaic")
    keys = ws.load_plan("compose_mosaic")
    assert [ws.load_part("compose_mosaic", k)["rows"] for k in keys[:-1]] == [512] * (len(keys) - 1)
    same_outputs(ws, before)
    assert kept == [True] * 2 * len(keys)  # every band's and index band's first level taken from beside it
    levels = every_level(ws)
    ws.forget_stage_report("compose_mosaic")  # and as a large mosaic's: the bands decoded again for the overviews
    for record in (ws.root / "parts" / "compose_mosaic").glob("part_*.json"):
        record.unlink()
    monkeypatch.setattr(compose_mosaic, "FIRST_LEVEL_MAX_PX", 0)
    kept.clear()
    run_stage(ws, "mosaic", "compose_mosaic")
    assert kept == [False] * 2 * len(keys)
    for ours, theirs in zip(every_level(ws), levels, strict=True):
        np.testing.assert_array_equal(ours, theirs)
    monkeypatch.setattr(compose_mosaic, "FIRST_LEVEL_MAX_PX", 1 << 27)
    assert not list(ws.root.rglob("*.level1.npz"))

    ws.forget_stage_report("compose_mosaic")
    for record in (ws.root / "parts" / "compose_mosaic").glob("part_*.json"):
        record.unlink()
    copy, copied = cog_writer._copy_tiles, list[str]()

    def killed(out: Any, source: Any) -> int:
        if source.path.name.startswith("band_") and len(copied) == 1:
            raise RuntimeError("worker killed")
        copied.extend([source.path.name] if source.path.name.startswith("band_") else [])
        return copy(out, source)

    monkeypatch.setattr(cog_writer, "_copy_tiles", killed)
    with pytest.raises(RuntimeError, match="worker killed"):
        run_stage(ws, "mosaic", "compose_mosaic")
    monkeypatch.setattr(cog_writer, "_copy_tiles", copy)
    folder = ws.root / "parts" / "compose_mosaic"
    assert len(copied) == 1 and not any((folder / name).exists() for name in copied)
    older = folder / f"band_{int(keys[2]):07d}.tif"  # not copied yet: now as an older version wrote it
    with rasterio.open(older) as src:
        width, height = src.width, src.height
    with open_block_writer(older, width, height, None, None, compress="zstd") as write:
        write(Window(0, 0, width, height), np.zeros((height, width, 3), np.uint8), np.ones((height, width), bool))
    (ws.root / ".mosaic.tif.killed.tif").write_bytes(b"half a COG")  # what a killed process's atomic write leaves
    kept.clear()
    run_stage(ws, "mosaic", "compose_mosaic")
    same_outputs(ws, before)
    # the bands composed again (the one copied, the older one) kept their first levels; the stopped finish had used
    # up the others' (those bands decoded again, to the same overviews), not yet the index bands' (stopped before)
    assert kept == [n in (0, 2) for n in range(len(keys))] + [True] * len(keys), kept
    for ours, theirs in zip(every_level(ws), levels, strict=True):
        np.testing.assert_array_equal(ours, theirs)


def test_an_overview_row_that_cannot_be_written_fails_the_cog(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Overview tile rows are written on a thread of their own while the next are made: a row that cannot be written
    (a full disk) fails the COG with its error, and no COG is left."""
    rgb, mask, index = scene(700, 2100)
    bands, _ = write_bands(tmp_path, rgb, mask, index, "deflate")
    written = []
    write_file = cog_writer._LevelOut._write_file

    def full_disk(level: Any, path: Path, values: np.ndarray, covered: np.ndarray | None) -> None:
        if written:
            raise OSError(errno.ENOSPC, "No space left on device")
        written.append(path)
        write_file(level, path, values, covered)

    monkeypatch.setattr(cog_writer._LevelOut, "_write_file", full_disk)
    with pytest.raises(OSError, match="No space left"):
        write_cog_from_bands(
            tmp_path / "ours.tif", bands, width=700, height=2100, crs=EPSG, transform=TRANSFORM,
            compression="deflate", kind="rgb", tags={}, scratch=tmp_path / "m.tmp.tif",
        )  # fmt: skip
    assert len(written) == 1 and not (tmp_path / "ours.tif").exists()


@pytest.mark.parametrize("kind", ["rgb", "index"])
def test_an_overview_level_holds_its_own_rows_only(tmp_path: Path, kind: str) -> None:
    # a tall raster's top level receives a row per band and writes once it has a tile row of them: until then
    # it must hold those rows, not the bands they came from
    width, bands = 2048, 40
    levels = [
        cog_writer._LevelOut(
            tmp_path / f"level{factor}", -(-width // factor), -(-512 * bands // factor), "deflate", kind
        )  # type: ignore[arg-type]
        for factor in cog_writer.overview_levels(width, 512 * bands)
    ]
    chain: Any = cog_writer._NearestChain(levels) if kind == "index" else cog_writer._AverageChain(levels)
    rng = np.random.default_rng(0)
    for n in range(bands):
        if kind == "index":
            first: Any = rng.integers(0, 40, (256, width // 2), dtype=np.uint16)
        else:
            first = (
                rng.integers(0, 1021, (256, width // 2, 3), dtype=np.uint16),
                np.full((256, width // 2), 4, np.uint16),
            )
        chain.add(first, 512 * n)
    for level in levels:
        held = sum((v if v.base is None else v.base).nbytes for v in level.values)
        own = sum(v.nbytes for v in level.values)
        assert held <= own + 512 * level.width * 3, (level.width, held, own)  # at most one array shared


def test_pooling_by_blocks_of_columns_equals_pooling_whole(monkeypatch: pytest.MonkeyPatch) -> None:
    """The overviews' 2x2 sums and averages on several threads, by blocks of columns, an odd width and height:
    the same numbers as one pass (blocks start at even columns, so no 2x2 block is cut)."""
    monkeypatch.setattr(cog_writer, "usable_cores", lambda: 3)
    monkeypatch.setattr(cog_writer, "_COLUMNS_PX", 16)
    rng = np.random.default_rng(5)
    rgb = rng.integers(0, 256, (9, 101, 3), dtype=np.uint8)
    covered = (rng.random((9, 101)) > 0.3).astype(np.uint8)
    sums, counts = cog_writer._pool(np.where(covered[..., None] > 0, rgb, np.uint8(0)), covered, np.uint16)
    for wide in (np.uint32, np.uint64):
        whole = cog_writer._pool(sums, counts, wide)
        blocks = cog_writer._by_columns(lambda s, c, wide=wide: cog_writer._pool(s, c, wide), sums, counts)
        assert all(np.array_equal(a, b) and a.dtype == b.dtype for a, b in zip(whole, blocks, strict=True))
        average = partial(cog_writer._average, full=16)
        assert np.array_equal(cog_writer._by_columns(average, *whole), average(*whole))
    assert cog_writer._by_columns(partial(cog_writer._average, full=4), sums, counts).shape == (5, 51, 3)


@pytest.mark.parametrize(("full", "dtype"), [(4, np.uint16), (64, np.uint32)])
def test_averages_of_whole_blocks_by_shift_equal_the_division(full: int, dtype: type) -> None:
    """A level's averages: whole blocks (``full`` pixels covered) by a shift, cut ones (a mask's edge) by division,
    uncovered ones 0; every one the covered pixels' mean rounded half up, as the integer oracle has it."""
    rng = np.random.default_rng(3)
    counts = rng.choice([0, 1, full - 1, full, full], size=(40, 60)).astype(dtype)
    sums = (rng.integers(0, 256, (40, 60, 3)) * counts[..., None]).astype(dtype)  # a mean up to 255
    sums[..., 1] = np.minimum(sums[..., 1] + counts // 2, 255 * counts)  # halves: rounded up
    expected = (2 * sums.astype(np.int64) + counts[..., None]) // (2 * np.maximum(counts, 1)[..., None])
    assert np.array_equal(cog_writer._average(sums, counts, full), expected)
    assert (counts == full).any() and ((counts != full) & (counts > 0)).any() and (counts == 0).any()


def test_tiles_copied_by_python_when_the_kernel_cannot_are_the_same_bytes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The COG's tiles go from band to COG by ``os.copy_file_range``; where it copies a tile in pieces, or fails
    (another file system: EXDEV), the same file comes out."""
    rgb, mask, index = scene(1300, 1100)

    def cog(name: str) -> bytes:
        folder = tmp_path / name
        folder.mkdir()
        mosaic, _ = assemble(folder, *write_bands(folder, rgb, mask, index, "deflate"), (1300, 1100), "deflate")
        return mosaic.read_bytes()

    kernel = cog("kernel")
    real = os.copy_file_range
    monkeypatch.setattr(os, "copy_file_range", lambda src, dst, count, offset: real(src, dst, min(count, 999), offset))
    pieces = cog("pieces")

    def refuse(*_: object) -> int:
        raise OSError(errno.EXDEV, "cross-device")

    monkeypatch.setattr(os, "copy_file_range", refuse)
    for other in (pieces, cog("python")):  # the same but the time written ("YYYY:MM:DD HH:MM:SS")
        assert len(other) == len(kernel)
        differ = np.flatnonzero(np.frombuffer(other, np.uint8) != np.frombuffer(kernel, np.uint8))
        assert differ.size == 0 or differ.max() - differ.min() < 19
