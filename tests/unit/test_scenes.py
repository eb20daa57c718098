"""The synthetic flight generator tells the truth: frames, homographies, EXIF and georeference agree."""

from __future__ import annotations

import functools
import math
import struct
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image, UnidentifiedImageError
from pyproj import Transformer

from tests.scenes import SyntheticFlight, make_flight, make_texture, write_bad_files

GPS_IFD = 0x8825
EXIF_IFD = 0x8769


@pytest.fixture(scope="module")
def strip(tmp_path_factory: pytest.TempPathFactory) -> SyntheticFlight:
    return make_flight(tmp_path_factory.mktemp("strip"), perspective=0.02, seed=3)


@pytest.fixture(scope="module")
def grid(tmp_path_factory: pytest.TempPathFactory) -> SyntheticFlight:
    return make_flight(
        tmp_path_factory.mktemp("grid"),
        layout="grid",
        n_frames=8,
        rotation_deg=0.0,
        scale_jitter=0.0,
        frame_size=(320, 240),
        seed=4,
    )


def read_bgr(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, path
    return img


def sample_texture(flight: SyntheticFlight, homography: np.ndarray) -> np.ndarray:
    """``(h, w, 3) float32``: the texture, bilinear, at ``homography @ (x, y)`` of each frame pixel."""
    w, h = flight.frame_size
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([xs, ys, np.ones_like(xs)], axis=-1) @ homography.T
    map_x = (pts[..., 0] / pts[..., 2]).astype(np.float32)
    map_y = (pts[..., 1] / pts[..., 2]).astype(np.float32)
    return cv2.remap(flight.texture, map_x, map_y, cv2.INTER_LINEAR).astype(np.float32)


def exif_of(path: Path) -> Image.Exif:
    with Image.open(path) as img:
        return img.getexif()


def dms_to_deg(dms: tuple, ref: str) -> float:
    deg = float(dms[0]) + float(dms[1]) / 60 + float(dms[2]) / 3600
    return -deg if ref in ("S", "W") else deg


def footprint_overlap(flight: SyntheticFlight, i: int, j: int) -> float:
    """Area shared by the footprints of frames ``i`` and ``j`` as a fraction of one frame's area."""
    area, _ = cv2.intersectConvexConvex(
        flight.corners_texture(i).astype(np.float32), flight.corners_texture(j).astype(np.float32)
    )
    w, h = flight.frame_size
    return area / (w * h)


def test_texture_is_deterministic_for_a_seed() -> None:
    a, b, c = make_texture(200, 300, seed=5), make_texture(200, 300, seed=5), make_texture(200, 300, seed=6)
    assert a.shape == (200, 300, 3) and a.dtype == np.uint8
    assert np.array_equal(a, b)
    assert np.abs(a.astype(int) - c).mean() > 20


def test_texture_has_keypoints_everywhere() -> None:
    grey = cv2.cvtColor(make_texture(512, 512, seed=1), cv2.COLOR_BGR2GRAY)
    pts = np.array([kp.pt for kp in cv2.SIFT.create().detect(grey, None)])
    counts, _, _ = np.histogram2d(pts[:, 0], pts[:, 1], bins=4, range=[[0, 512], [0, 512]])
    assert len(pts) > 2000
    assert counts.min() > 60, counts


def test_texture_is_not_periodic() -> None:
    grey = cv2.cvtColor(make_texture(512, 512, seed=2), cv2.COLOR_BGR2GRAY)
    for x, y in [(64, 64), (224, 224), (384, 96), (100, 400)]:
        score = cv2.matchTemplate(grey, grey[y : y + 64, x : x + 64], cv2.TM_CCOEFF_NORMED)
        assert score[y, x] > 0.999
        rows, cols = np.ogrid[: score.shape[0], : score.shape[1]]
        score[np.hypot(rows - y, cols - x) < 16] = -1  # the patch itself and its small shifts
        # A periodic texture would score ~1 at another place; ours shares only blobs of colour.
        assert score.max() < 0.8, (x, y)


def test_frame_pixels_equal_texture_at_homography(strip: SyntheticFlight) -> None:
    for i in (0, len(strip.paths) // 2, len(strip.paths) - 1):
        frame = read_bgr(strip.paths[i]).astype(np.float32)
        assert frame.shape == (strip.frame_size[1], strip.frame_size[0], 3)
        error = np.abs(frame - sample_texture(strip, strip.homographies[i])).mean()
        shifted = np.array([[1, 0, 1.0], [0, 1, 0], [0, 0, 1]]) @ strip.homographies[i]
        error_shifted = np.abs(frame - sample_texture(strip, shifted)).mean()
        assert error < 5.0, f"frame {i}: mean abs error {error:.2f} grey levels"
        assert error_shifted > 2 * error  # a 1 px error in the truth would show


def test_frames_lie_inside_texture_with_margin(strip: SyntheticFlight, grid: SyntheticFlight) -> None:
    for flight in (strip, grid):
        tex_h, tex_w = flight.texture.shape[:2]
        corners = np.vstack([flight.corners_texture(i) for i in range(len(flight.paths))])
        assert corners.min() > 16
        assert corners[:, 0].max() < tex_w - 16 and corners[:, 1].max() < tex_h - 16


def test_strip_frames_overlap_as_asked(tmp_path: Path) -> None:
    exact = make_flight(tmp_path / "exact", n_frames=4, frame_size=(160, 120), rotation_deg=0, scale_jitter=0)
    assert [footprint_overlap(exact, i, i + 1) for i in range(3)] == pytest.approx([0.6] * 3, abs=1e-4)
    jittered = make_flight(tmp_path / "jitter", n_frames=6, frame_size=(160, 120), overlap=0.7)
    overlaps = [footprint_overlap(jittered, i, i + 1) for i in range(5)]
    assert min(overlaps) > 0.5 and max(overlaps) < 0.8
    assert footprint_overlap(jittered, 0, 5) == 0  # frames far apart along the strip share nothing


def test_grid_is_two_serpentine_lines(grid: SyntheticFlight) -> None:
    centres = np.array([grid.frame_center_utm(i) for i in range(8)])
    assert np.allclose(centres[:4, 1], centres[0, 1]) and np.allclose(centres[4:, 1], centres[4, 1])
    assert centres[0, 1] > centres[4, 1]  # first line is the northern one
    assert np.all(np.diff(centres[:4, 0]) > 0) and np.all(np.diff(centres[4:, 0]) < 0)
    assert footprint_overlap(grid, 3, 4) == pytest.approx(0.3, abs=1e-3)  # the turn: side overlap
    assert footprint_overlap(grid, 0, 7) == pytest.approx(0.3, abs=1e-3)
    assert footprint_overlap(grid, 0, 1) == pytest.approx(0.6, abs=1e-3)


def test_nadir_flight_has_similarity_homographies(tmp_path: Path) -> None:
    flight = make_flight(tmp_path, n_frames=6, frame_size=(160, 120), rotation_deg=8, scale_jitter=0.05)
    for hom in flight.homographies:
        a = hom[:2, :2]
        assert hom.dtype == np.float64 and hom.shape == (3, 3)
        assert np.array_equal(hom[2], [0, 0, 1])
        assert a[0, 0] == pytest.approx(a[1, 1]) and a[0, 1] == pytest.approx(-a[1, 0])
        assert 0.95 <= math.sqrt(np.linalg.det(a)) <= 1.05
        assert abs(math.degrees(math.atan2(a[1, 0], a[0, 0]))) <= 8


def test_perspective_terms_are_bounded_with_zero_mean(strip: SyntheticFlight) -> None:
    w, h = strip.frame_size
    cx, cy = (w - 1) / 2, (h - 1) / 2
    terms = []
    for hom in strip.homographies:
        a, b = hom[2, 0] / hom[2, 2], hom[2, 1] / hom[2, 2]
        k = 1 / (1 + a * cx + b * cy)  # undo the normalisation H[2, 2] = 1 of T(c) R S P T(-centre)
        terms.append((k * a * w, k * b * h))
    terms_arr = np.array(terms)
    assert np.abs(terms_arr).max() <= 0.02 + 1e-12
    assert np.abs(terms_arr).max() > 0.005
    assert np.allclose(terms_arr.mean(axis=0), 0, atol=1e-12)


def test_georeference_is_north_up_utm_centred_on_origin(strip: SyntheticFlight) -> None:
    assert strip.epsg == 32615
    t = strip.texture_to_utm
    assert t[0, 0] == strip.gsd_m == 0.05 and t[1, 1] == -0.05 and t[0, 1] == t[1, 0] == 0
    tex_h, tex_w = strip.texture.shape[:2]
    east, north, _ = t @ [(tex_w - 1) / 2, (tex_h - 1) / 2, 1]
    lon, lat = Transformer.from_crs(32615, 4326, always_xy=True).transform(east, north)
    assert (lat, lon) == pytest.approx((29.76, -95.37), abs=1e-9)
    a, b, c, d, e, f = strip.texture_geotransform()
    assert (a * 0.5 + b * 0.5 + c, d * 0.5 + e * 0.5 + f) == pytest.approx(tuple(t[:2, 2]))


def test_exif_gps_reads_back(strip: SyntheticFlight) -> None:
    assert strip.gps is not None and len(strip.gps) == len(strip.paths)
    to_utm = Transformer.from_crs(4326, strip.epsg, always_xy=True)
    for i, path in enumerate(strip.paths):
        gps = exif_of(path).get_ifd(GPS_IFD)
        lat, lon = dms_to_deg(gps[2], gps[1]), dms_to_deg(gps[4], gps[3])
        lat_true, lon_true, alt_true = strip.gps[i]
        assert abs(lat - lat_true) < 1e-6 and abs(lon - lon_true) < 1e-6
        assert gps[1] == "N" and gps[3] == "W"
        assert float(gps[6]) == pytest.approx(alt_true) and gps[5] == b"\x00"
        assert np.allclose(to_utm.transform(lon, lat), strip.frame_center_utm(i), atol=0.01)


def test_exif_gps_uses_standard_tag_types(strip: SyntheticFlight) -> None:
    # Read the raw TIFF entries, not Pillow's interpretation, to see what other EXIF readers get.
    with Image.open(strip.paths[0]) as img:
        tiff = img.info["exif"][6:]  # after "Exif\0\0"
    order = "<" if tiff[:2] == b"II" else ">"

    def entries(offset: int) -> dict[int, tuple[int, int, int]]:
        """Tag -> (type, count, value or offset) of the IFD at ``offset``."""
        (count,) = struct.unpack_from(order + "H", tiff, offset)
        rows = (struct.unpack_from(order + "HHII", tiff, offset + 2 + 12 * k) for k in range(count))
        return {tag: (kind, n, value) for tag, kind, n, value in rows}

    ifd0 = entries(struct.unpack_from(order + "I", tiff, 4)[0])
    gps = {tag: row[:2] for tag, row in entries(ifd0[GPS_IFD][2]).items()}
    assert gps[2] == (5, 3) and gps[4] == (5, 3) and gps[6] == (5, 1)  # RATIONAL
    assert gps[1] == (2, 2) and gps[3] == (2, 2) and gps[5] == (1, 1) and gps[0] == (1, 4)


def test_exif_camera_fields(strip: SyntheticFlight) -> None:
    stamps = []
    for path in strip.paths:
        exif = exif_of(path)
        sub = exif.get_ifd(EXIF_IFD)
        assert (exif[0x010F], exif[0x0110]) == ("Fotoskhema", "Synthetic")
        assert float(sub[0x920A]) == pytest.approx(8.8)
        w = strip.frame_size[0]
        assert 60.0 * 36 / (sub[0xA405] * w) == pytest.approx(strip.gsd_m, rel=0.01)  # GSD from EXIF
        stamps.append(sub[0x9003])
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)


def test_no_gps_ifd_without_gps(tmp_path: Path) -> None:
    flight = make_flight(tmp_path, n_frames=2, frame_size=(160, 120), gps=False)
    assert flight.gps is None
    for path in flight.paths:
        exif = exif_of(path)
        assert GPS_IFD not in exif and not exif.get_ifd(GPS_IFD)
        assert float(exif.get_ifd(EXIF_IFD)[0x920A]) == pytest.approx(8.8)


def test_flight_is_deterministic_for_a_seed(tmp_path: Path) -> None:
    small = functools.partial(make_flight, n_frames=3, frame_size=(160, 120), perspective=0.02)
    a, b, c = small(tmp_path / "a", seed=7), small(tmp_path / "b", seed=7), small(tmp_path / "c", seed=8)
    assert [p.name for p in a.paths] == ["frame_000.jpg", "frame_001.jpg", "frame_002.jpg"]
    assert [p.read_bytes() for p in a.paths] == [p.read_bytes() for p in b.paths]
    assert all(np.array_equal(x, y) for x, y in zip(a.homographies, b.homographies, strict=True))
    assert a.paths[0].read_bytes() != c.paths[0].read_bytes()
    assert not np.allclose(a.homographies[0], c.homographies[0])


def test_default_flight_is_fast(tmp_path: Path) -> None:
    start = time.perf_counter()
    make_flight(tmp_path, n_frames=8, frame_size=(640, 480))
    assert time.perf_counter() - start < 2.0


def test_bad_files_are_bad(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    bad = write_bad_files(tmp_path)
    assert set(bad) == {"not_image", "truncated", "empty", "bomb"}
    assert all(p.suffix == ".jpg" for p in bad.values())
    assert bad["empty"].stat().st_size == 0
    with pytest.raises(UnidentifiedImageError):
        Image.open(bad["not_image"])
    with Image.open(bad["truncated"]) as img, pytest.raises(OSError):
        img.load()
    assert bad["bomb"].stat().st_size < 100_000
    with pytest.raises(Image.DecompressionBombError):
        Image.open(bad["bomb"])
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", None)
    with Image.open(bad["bomb"]) as img:
        assert img.size == (50_000, 50_000) and img.format == "JPEG"


@pytest.mark.parametrize(
    "kwargs",
    [
        {"layout": "spiral"},
        {"overlap": 1.0},
        {"n_frames": 0},
        {"layout": "grid", "n_frames": 1},
        {"perspective": 0.9},
        {"scale_jitter": -0.1},
        {"frame_size": (8, 8)},
    ],
)
def test_invalid_arguments_raise(tmp_path: Path, kwargs: dict) -> None:
    with pytest.raises(ValueError):
        make_flight(tmp_path, **kwargs)
    assert not list(tmp_path.iterdir())  # nothing written
