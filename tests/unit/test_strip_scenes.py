"""The synthetic aerial strip generator tells the truth: pixels, homographies, files and GPS agree."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import rasterio
from pyproj import Transformer
from rasterio.enums import Compression, PhotometricInterp

from tests.strip_scenes import STRIP_ROWS, TILE, GroundTexture, SyntheticStrip, make_strip

SMALL = (6000, 400)  # (width, height): long across track, as the real 75000 x 1800 frame
PATCH = 15  # half side of the NCC patches, px


# Raw frames carry no georeference, on purpose: finding it is the pipeline's job.
pytestmark = pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")


@pytest.fixture(scope="module")
def strip(tmp_path_factory: pytest.TempPathFactory) -> SyntheticStrip:
    return make_strip(tmp_path_factory.mktemp("strip"), 3, frame_size=SMALL, seed=5)


def _read(path: Path) -> np.ndarray:
    """``(H, W, 3)`` RGB of a frame file."""
    with rasterio.open(path) as src:
        return np.moveaxis(src.read(), 0, 2)


def _grey(rgb: np.ndarray) -> np.ndarray:
    return rgb.astype(np.float32).mean(axis=2)


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def _map(hom: np.ndarray, points: np.ndarray) -> np.ndarray:
    mapped = np.column_stack([points, np.ones(len(points))]) @ hom.T
    return mapped[:, :2] / mapped[:, 2:3]


def _overlap_points(strip: SyntheticStrip, i: int, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Integer px of frame ``i`` and their true px in frame ``i + 1``, both away from borders and CCD seams."""
    w, h = strip.frame_size
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.integers(0, w, 20 * count), rng.integers(0, h, 20 * count)]).astype(np.float64)
    other = _map(np.linalg.inv(strip.homographies[i + 1]) @ strip.homographies[i], points)
    seams = strip.ccd_seams()
    margin = PATCH + 3

    def clear(p: np.ndarray) -> np.ndarray:
        inside = (p[:, 0] > margin) & (p[:, 0] < w - margin) & (p[:, 1] > margin) & (p[:, 1] < h - margin)
        return inside & (np.abs(p[:, :1] - seams[None, :]).min(axis=1) > margin)

    keep = np.flatnonzero(clear(points) & clear(other))[:count]
    return points[keep], other[keep]


def test_same_seed_gives_the_same_files_rendered_in_one_process_or_two(tmp_path: Path) -> None:
    args: dict[str, Any] = {"n_frames": 2, "frame_size": (4200, 160), "seed": 11}
    first, second = make_strip(tmp_path / "a", **args), make_strip(tmp_path / "b", processes=2, **args)
    for a, b in zip(first.paths + [first.gps_path], second.paths + [second.gps_path], strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name
    other = make_strip(tmp_path / "c", **{**args, "seed": 12})
    assert not np.array_equal(_read(first.paths[0]), _read(other.paths[0]))


def test_ground_is_the_same_whatever_window_it_is_computed_in() -> None:
    ground = GroundTexture(seed=3, field_angle=0.2, road_angle=1.4)
    big = ground.raster(-1500, 700, 2100, 900)
    small = ground.raster(-1013, 1001, 333, 257)  # an odd offset into ``big``, odd sizes
    np.testing.assert_array_equal(small, big[301:558, 487:820])
    # Between pixels it is their bicubic interpolation; at pixel centres, the raster itself.
    gx, gy = np.meshgrid(np.arange(-1013.0, -1003.0), np.arange(1001.0, 1005.0))
    np.testing.assert_allclose(ground.sample(gx, gy), small[:4, :10], atol=1e-3)


def test_ground_has_texture_at_every_scale() -> None:
    ground = GroundTexture(seed=4, field_angle=0.3, road_angle=1.9)
    grey = ground.raster(0, 0, 4096, 2048).mean(axis=2)
    for level in range(6):  # 1 to 32 ground px per pixel: a coarse matching level still has contrast
        reduced = cv2.resize(grey, None, fx=0.5**level, fy=0.5**level, interpolation=cv2.INTER_AREA)
        detail = reduced - cv2.GaussianBlur(reduced, (0, 0), 2.0)
        assert detail.std() > 2.0, level


def test_frame_pixels_are_the_ground_under_the_truth(tmp_path: Path) -> None:
    strip = make_strip(tmp_path, 1, frame_size=(2500, 120), compression="none", seed=6, vignetting=0.2)
    frame = _read(strip.paths[0]).astype(np.float64)
    rng = np.random.default_rng(0)
    xs, ys = rng.integers(0, 2500, 400), rng.integers(0, 120, 400)
    ground = _map(strip.homographies[0], np.column_stack([xs, ys]).astype(np.float64))
    rgb = strip.ground.sample(ground[:, :1], ground[:, 1:]).reshape(-1, 3).astype(np.float64)
    w, h = strip.frame_size
    segment = (xs + 0.5) * len(strip.ccd_gains) // w
    u, v = (xs - (w - 1) / 2) / (w / 2), (ys - (h - 1) / 2) / (h / 2)
    gain = strip.frame_gains[0] * strip.ccd_gains[segment.astype(int)] * (1 - 0.2 * (u**2 + v**2) / 2)
    expected = np.clip(rgb * gain[:, None], 0, 255)
    assert np.abs(frame[ys, xs] - expected).max() <= 0.51  # rounding to uint8 only


def test_truth_maps_each_pixel_to_the_same_ground_in_the_next_frame(strip: SyntheticStrip) -> None:
    for i in range(len(strip.paths) - 1):
        this, following = _grey(_read(strip.paths[i])), _grey(_read(strip.paths[i + 1]))
        points, other = _overlap_points(strip, i, 40, seed=i)
        assert len(points) >= 30
        size = (2 * PATCH + 1, 2 * PATCH + 1)
        true, shifted = [], []
        for (x, y), (ox, oy) in zip(points.astype(int), other, strict=True):
            patch = this[y - PATCH : y + PATCH + 1, x - PATCH : x + PATCH + 1]
            true.append(_ncc(patch, cv2.getRectSubPix(following, size, (float(ox), float(oy)))))
            shifted.append(_ncc(patch, cv2.getRectSubPix(following, size, (float(ox) + 2, float(oy) - 1))))
        assert min(true) > 0.9, i
        assert np.median(shifted) < 0.85, i  # the check would see a 2 px error


@pytest.mark.parametrize("overlap", [0.55, 0.7])
def test_overlap_matches_the_request(tmp_path: Path, overlap: float) -> None:
    strip = make_strip(tmp_path, 4, frame_size=(1200, 200), overlap=overlap, compression="none", seed=7)
    w, h = strip.frame_size
    xs, ys = np.meshgrid(np.arange(0, w, 4.0), np.arange(0, h, 2.0))
    grid = np.column_stack([xs.ravel(), ys.ravel()])
    for i in range(3):
        other = _map(np.linalg.inv(strip.homographies[i + 1]) @ strip.homographies[i], grid)
        inside = (other[:, 0] > -0.5) & (other[:, 0] < w - 0.5) & (other[:, 1] > -0.5) & (other[:, 1] < h - 0.5)
        assert inside.mean() == pytest.approx(overlap, abs=0.02)
        # Along track is the short side: frame i + 1 lies north, its bottom rows on frame i's top rows.
        centre = _map(strip.homographies[i + 1], np.array([[(w - 1) / 2, (h - 1) / 2]]))
        assert _map(np.linalg.inv(strip.homographies[i]), centre)[0, 1] == pytest.approx(
            (h - 1) / 2 - (1 - overlap) * h, abs=0.02 * h
        )


@pytest.mark.parametrize(
    ("compression", "tiled", "bigtiff", "dtype"),
    [
        ("jpeg", True, False, "uint8"),
        ("jpeg", False, True, "uint8"),
        ("none", True, True, "uint16"),
        ("none", False, False, "uint8"),
    ],
)
def test_files_are_what_was_asked(tmp_path: Path, compression: str, tiled: bool, bigtiff: bool, dtype: str) -> None:
    size = (2100, 100)
    strip = make_strip(
        tmp_path, 1, frame_size=size, compression=compression, tiled=tiled, bigtiff=bigtiff, dtype=dtype, seed=8
    )
    path = strip.paths[0]
    with rasterio.open(path) as src:
        assert (src.width, src.height, src.count, src.dtypes) == (*size, 3, (dtype,) * 3)
        assert src.block_shapes[0] == ((TILE, TILE) if tiled else (STRIP_ROWS, size[0]))
        if compression == "jpeg":
            assert (src.compression, src.photometric) == (Compression.jpeg, PhotometricInterp.ycbcr)
        else:
            assert src.compression is None or src.compression == Compression.none
        pixels = src.read()
    assert path.read_bytes()[2:4] == (b"+\x00" if bigtiff else b"*\x00")  # TIFF version 43 or 42, little-endian
    assert not list(path.parent.glob("*.part"))
    if dtype == "uint16":
        assert pixels.max() > 255 * 64  # the 8-bit scale times 256
    assert 60 < pixels.mean() / (256 if dtype == "uint16" else 1) < 200


def test_gps_noise_has_the_requested_spread(tmp_path: Path) -> None:
    strip = make_strip(tmp_path, 150, frame_size=(64, 32), gps_noise_m=3.0, compression="none", seed=9)
    to_utm = Transformer.from_crs(4326, strip.epsg, always_xy=True)
    true = np.array([to_utm.transform(lon, lat) + (alt,) for lat, lon, alt in strip.gps_true])
    noisy = np.array([to_utm.transform(lon, lat) + (alt,) for lat, lon, alt in strip.gps_noisy])
    centres = np.array([strip.frame_center_utm(i) for i in range(150)])
    np.testing.assert_allclose(true[:, :2], centres, atol=0.01)
    np.testing.assert_allclose(true[:, 2], 8000.0)
    error = noisy - true
    np.testing.assert_allclose(error.std(axis=0), 3.0, rtol=0.15)
    assert np.all(np.abs(error.mean(axis=0)) < 3 * 3.0 / np.sqrt(150))


def test_gps_side_file_lists_every_frame(strip: SyntheticStrip) -> None:
    with strip.gps_path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["name", "lat", "lon", "alt", "accuracy"]
    assert [r["name"] for r in rows] == [p.name for p in strip.paths]
    written = np.array([[float(r["lat"]), float(r["lon"]), float(r["alt"])] for r in rows])
    np.testing.assert_allclose(written, np.array(strip.gps_noisy), atol=1e-6)
    assert {float(r["accuracy"]) for r in rows} == {strip.gps_noise_m}
    gps_file = pytest.importorskip("workers.gps_file")
    fixes = gps_file.parse_gps_file("gps.csv", strip.gps_path.read_text()).fixes
    assert [fix.name for fix in fixes] == [p.name for p in strip.paths]


def test_ccd_gains_and_seams(strip: SyntheticStrip) -> None:
    assert strip.ccd_gains.shape == (32,)
    assert np.all(np.abs(strip.ccd_gains - 1) <= 0.03) and strip.ccd_gains.std() > 0.005
    np.testing.assert_allclose(np.diff(strip.ccd_seams()), SMALL[0] / 32)


@pytest.mark.parametrize(
    "bad",
    [
        {"dtype": "uint16"},  # JPEG in TIFF is 8-bit
        {"tiled": False, "frame_size": (70_000, 32)},  # a JPEG strip is at most 65500 px wide
        {"overlap": 1.0},
        {"compression": "lzw"},
        {"rotation_deg": 2.0},
        {"n_frames": 0},
    ],
)
def test_bad_arguments_are_refused(tmp_path: Path, bad: dict[str, Any]) -> None:
    args: dict[str, Any] = {"n_frames": 1, "frame_size": (64, 32), **bad}
    with pytest.raises(ValueError):
        make_strip(tmp_path, **args)
    assert not list(tmp_path.iterdir())
