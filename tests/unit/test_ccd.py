"""A strip camera's CCD gain steps, measured in the frames' own rows and undone in the mosaic."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio

from tests.strip_scenes import SyntheticStrip, make_strip
from workers.algorithms.mosaic import ccd_gains, column_brightness, compose_block, output_box
from workers.algorithms.mosaic.ccd import _row_steps, join_columns
from workers.photo_io import dct_block

WIDTH, HEIGHT, SEGMENTS = 6400, 400, 32


@pytest.fixture(scope="module")
def strip(tmp_path_factory: pytest.TempPathFactory) -> tuple[SyntheticStrip, list[np.ndarray]]:
    """Three JPEG-in-TIFF frames (quality 90) whose 32 sub-images carry gains within +-3 %, as the camera's do."""
    strip = make_strip(tmp_path_factory.mktemp("ccd"), 3, frame_size=(WIDTH, HEIGHT), ccd_step=0.03, seed=3)
    return strip, [_read_bgr(path) for path in strip.paths]


def _read_bgr(path: Path) -> np.ndarray:
    """A frame whole, BGR as the pipeline reads photos."""
    with rasterio.open(path) as src:
        return np.moveaxis(src.read(), 0, 2)[..., ::-1].copy()


def test_the_gains_are_found_from_the_rows(strip) -> None:
    truth, frames = strip
    found = ccd_gains(lambda k, c0, c1: frames[k][:, c0:c1], [0, 1, 2], WIDTH, SEGMENTS)
    error = np.log(found) - (np.log(truth.ccd_gains) - np.log(truth.ccd_gains).mean())
    # each step (what shows) to a tenth of its size; the gains drift a little as the steps add up from the left
    assert np.abs(np.diff(error)).mean() < 0.1 * np.abs(np.diff(np.log(truth.ccd_gains))).mean()
    assert np.abs(error).max() < 0.02, error
    opened: list[int] = []  # frame by frame, on threads: the same gains, each frame's joins read together

    def columns(k: int, c0: int, c1: int) -> np.ndarray:
        opened.append(k)
        return frames[k][:, c0:c1]

    assert np.array_equal(ccd_gains(columns, [0, 1, 2], WIDTH, SEGMENTS, threads=3), found)
    opened.clear()
    ccd_gains(columns, [0, 1, 2], WIDTH, SEGMENTS)
    assert opened == sorted(opened)
    flat = [np.full_like(f, 120) for f in frames]  # no steps at all: none found
    assert np.allclose(ccd_gains(lambda k, c0, c1: flat[k][:, c0:c1], [0, 1, 2], WIDTH, SEGMENTS), 1.0)


def test_the_steps_are_undone_in_the_mosaic(strip) -> None:
    truth, frames = strip
    found = ccd_gains(lambda k, c0, c1: frames[k][:, c0:c1], [0, 1, 2], WIDTH, SEGMENTS)
    to_frame = {0: np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])}  # output px -> frame 0 px
    sizes = {0: (WIDTH, HEIGHT)}
    boxes = {0: output_box(to_frame[0], sizes[0], WIDTH, HEIGHT)}
    args = (frames.__getitem__, sizes, to_frame, boxes, {0: np.ones(3)}, (0, 0, WIDTH, HEIGHT), 20.0)
    plain, _, _ = compose_block(*args)
    evened, _, _ = compose_block(*args, columns={0: column_brightness(WIDTH, found)})

    def steps(rgb: np.ndarray) -> float:
        inner = rgb[40:-40]  # away from the feathered edge
        return float(np.mean([abs(np.median(_row_steps(inner[:, j - 2 : j + 2]))) for j in join_columns(WIDTH, 32)]))

    assert steps(evened) < 0.15 * steps(plain), (steps(evened), steps(plain))


def test_a_join_inside_a_jpeg_block_is_measured_across_the_block(tmp_path: Path) -> None:
    """Joins every 250 px: 12 of 15 fall inside an 8 px JPEG block, whose quantised high frequencies smear the
    step over the block. Extrapolating across the join then finds about half of each step; the columns just
    outside the block find all of it, with more spread (20 frames of 600 rows here)."""
    width, segments, n = 4000, 16, 20
    strip = make_strip(tmp_path, n, (width, 600), overlap=0.55, ccd_step=0.03, ccd_segments=segments, seed=4)
    frames = [_read_bgr(path) for path in strip.paths]
    truth = np.diff(np.log(strip.ccd_gains))
    inside = join_columns(width, segments) % 8 != 0
    assert inside.sum() == 12

    def steps(blocks: dict[int, int] | None) -> tuple[float, float]:
        """The found steps inside blocks: their scale against the truth, and their mean error over the mean step."""
        gains = ccd_gains(lambda k, c0, c1: frames[k][:, c0:c1], list(range(n)), width, segments, blocks)
        found = np.diff(np.log(gains))[inside]
        scale = np.sum(found * truth[inside]) / np.sum(truth[inside] ** 2)
        return scale, np.abs(found - truth[inside]).mean() / np.abs(truth[inside]).mean()

    smeared, across = steps(None), steps(dict.fromkeys(range(n), 8))
    assert smeared[0] < 0.7, smeared  # measured: 0.48
    assert 0.85 < across[0] < 1.2 and across[1] < 0.45, across  # measured: 1.12 and 0.34 (0.53 extrapolated)
    assert {dct_block(strip.paths[0]), dct_block(tmp_path / "photo.JPG"), dct_block(tmp_path / "scan.png")} == {8, 1}
