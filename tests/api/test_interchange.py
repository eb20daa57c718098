"""Formats other tools read: the provenance tags of a mosaic COG (software, version, date, description).

(The STAC item, the WebMercatorQuad tile and WMTS routes and ``all.zip`` are not written yet.)
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import rasterio
from rasterio.windows import Window

from workers.raster_io import open_block_writer, translate_to_cog


def test_cog_tags_set_on_the_scratch_survive_the_cog_driver(tmp_path: Path) -> None:
    scratch, cog = tmp_path / "scratch.tif", tmp_path / "mosaic.tif"
    with open_block_writer(scratch, 1200, 700, 32630, [0.03, 0, 699_000, 0, -0.03, 5_630_000], compress=None) as w:
        w(Window(0, 0, 1200, 700), np.full((700, 1200, 3), 90, np.uint8), np.ones((700, 1200), bool))
    translate_to_cog(scratch, cog, "deflate", tags={"TIFFTAG_IMAGEDESCRIPTION": "Fotoskhema mosaic job, mode planar"})
    with rasterio.open(cog) as src:
        tags = src.tags()
        assert src.overviews(1) == [2, 4] and src.crs.to_epsg() == 32630
    assert tags["TIFFTAG_IMAGEDESCRIPTION"] == "Fotoskhema mosaic job, mode planar"
    assert re.fullmatch(r"Fotoskhema \d+\.\d+\.\d+\S*", tags["TIFFTAG_SOFTWARE"])
    assert re.fullmatch(r"\d{4}:\d\d:\d\d \d\d:\d\d:\d\d", tags["TIFFTAG_DATETIME"])
    assert not list(tmp_path.glob("*.aux.xml"))  # real TIFF tags, not a sidecar file


def test_without_tags_the_cog_has_none_of_ours(tmp_path: Path) -> None:
    scratch, cog = tmp_path / "scratch.tif", tmp_path / "mosaic.tif"
    with open_block_writer(scratch, 300, 200, None, None, compress=None) as w:
        w(Window(0, 0, 300, 200), np.zeros((200, 300, 3), np.uint8), np.ones((200, 300), bool))
    translate_to_cog(scratch, cog, "lzw")
    with rasterio.open(cog) as src:
        assert "TIFFTAG_SOFTWARE" not in src.tags()
