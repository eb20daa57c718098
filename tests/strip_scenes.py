"""Synthetic aerial strips of a multi-lens camera, at native size, with known ground truth.

A strip is a line of composite frames, each ``W x H`` px with the long side ``W`` across track (75000 x
1800 for the real camera), consecutive frames advancing along track (down the short side) by
``(1 - overlap) * H``. Unlike ``scenes.make_flight``, which cuts frames from one texture held in memory,
the ground here is a procedural function of ground-plane coordinates (``GroundTexture``), so a frame of
any size is rendered block by block (2048 columns, or bands of whole strips): the ground raster under a
block is computed and resampled through the frame's homography (bicubic), so no frame is ever held in
float and memory stays near 300 MB whatever the frame size. Frames are written by window into GeoTIFFs (JPEG in TIFF,
YCbCr, or uncompressed; tiled or striped; BigTIFF on request) and the noisy GPS goes to a CSV side file.

Pixel convention: OpenCV's, as in ``tests.scenes``: integer ``(x, y)`` is the centre of pixel ``[y, x]``.
Ground-plane px follow the same convention, north up (``y`` grows southwards); ``texture_to_utm`` maps them
to UTM metres. The flight heads north: frame ``x`` points east, frame ``y`` south, frame ``i + 1`` lies
north of frame ``i``, so the top rows of frame ``i`` are the bottom rows of frame ``i + 1``.

Radiometry of frame pixel ``(x, y)`` of frame ``i``: ``ground(H_i (x, y)) * frame_gain_i * ccd_gain_k(x) *
vignette(x, y)``, ``k = floor(x * ccd_segments / W)`` the CCD sub-image the pixel belongs to, and
``vignette = 1 - vignetting * (u**2 + v**2) / 2`` with ``u, v`` in ``[-1, 1]`` across the frame's width and
height (so the corners lose ``vignetting`` of their brightness, the long edges half of it).
"""

from __future__ import annotations

import csv
import dataclasses
import math
import multiprocessing
import warnings
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import rasterio
from pyproj import Transformer
from rasterio.errors import NotGeoreferencedWarning
from rasterio.windows import Window

from tests.scenes import _apply_homography, _georeference, _normalised, _perspective_terms, _translation

FULL_FRAME = (75_000, 1_800)  # (width, height) px of the real camera's composite frame
RENDER_COLUMNS = 2048  # columns of one rendered block: a multiple of every tile size used here
TILE = 256  # tile side of tiled frames; JPEG in TIFF needs multiples of 16
STRIP_ROWS = 16  # rows per strip of striped frames: one YCbCr 4:2:0 MCU row is 16 rows
BAND_PIXELS = 16_000_000  # pixels rendered and written at a time for striped frames (whole strips)
JPEG_MAX_SIDE = 65500  # GDAL's limit on a JPEG-compressed strip's width
GPS_FILE = "gps.csv"
# Grey value noise, one octave per pyramid level k = 1..len: lattice cell 2**k ground px, amplitude in 8-bit
# grey levels. Fine octaves for native-resolution NCC, coarse ones so a 1/32 pyramid level has texture too.
OCTAVE_AMPLITUDES = (16.0, 16.0, 17.0, 17.0, 17.0, 17.0, 17.0, 17.0, 17.0, 17.0, 17.0)
MARGIN = 3  # px kept around each pyramid level's needed range: bicubic reads 2 px beyond
FIELD_SIZE = 420.0  # ground px: side of a field parcel
FIELD_CONTRAST = 28.0  # grey levels: spread of the per-field brightness
FIELD_TINT = 14.0  # grey levels: spread of each field's colour per channel
HEDGE_HALF_WIDTH = 2.5  # ground px: the dark border between fields, each side of the parcel edge
HEDGE_LEVEL = -40.0  # grey levels, relative to mid grey
ROAD_SPACING = 1700.0  # ground px between candidate road lines
ROAD_HALF_WIDTH = 4.0  # ground px
ROAD_BRIGHTNESS = 60.0  # grey levels added on a road
ROAD_FRACTION = 0.4  # fraction of candidate lines that are roads


@dataclass(frozen=True)
class GroundTexture:
    """A seeded, unbounded RGB ground: band-limited value noise, field parcels with hedges, and roads.

    The ground is a raster on the integer ground px (``raster``) whose every value depends only on the
    pixel and the seed, whatever window it is computed in, and between pixels its bicubic interpolation
    (``sample``). So frames rendered separately, block by block, agree wherever they overlap.

    The noise is built coarse to fine as a Laplacian pyramid is collapsed: level ``k`` (pixel ``2**k``
    ground px) is the bicubic 2x upsampling of level ``k + 1`` plus hashed lattice values, so each octave
    costs a quarter of the next finer one and the whole ground about 4/3 of one full-resolution pass.
    """

    seed: int
    field_angle: float = 0.0  # radians: orientation of the field grid
    road_angle: float = 1.0  # radians: orientation of the road lines

    def raster(self, x0: int, y0: int, width: int, height: int) -> np.ndarray:
        """``(height, width, 3) float32`` RGB, 8-bit grey levels (not clipped), at ground px
        ``x0 .. x0 + width - 1``, ``y0 .. y0 + height - 1``."""
        if width < 1 or height < 1 or width >= 32767 or height >= 32767:
            raise ValueError(f"a ground raster is 1-32766 px a side, got {width}x{height}")
        xs = np.arange(x0, x0 + width, dtype=np.float64)
        ys = np.arange(y0, y0 + height, dtype=np.float64)
        grey = self._noise(x0, y0, width, height)
        grey += self._roads(xs, ys)
        colour, inside = self._fields(xs, ys)
        # Inside a parcel its colour, on a hedge the hedge's: ``inside`` ramps over 1 px, so no aliasing.
        rgb = colour * inside[..., None]
        rgb += ((1 - inside) * HEDGE_LEVEL + grey + 128)[..., None]
        return rgb

    def sample(self, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
        """``(*gx.shape, 3) float32`` RGB at ground px ``gx, gy`` (2-D float arrays of one shape)."""
        if gx.shape != gy.shape or gx.ndim != 2:
            raise ValueError(f"gx, gy must be 2-D arrays of one shape, got {gx.shape}, {gy.shape}")
        x0, y0 = math.floor(gx.min()) - MARGIN, math.floor(gy.min()) - MARGIN
        width, height = math.ceil(gx.max()) + MARGIN + 1 - x0, math.ceil(gy.max()) + MARGIN + 1 - y0
        ground = self.raster(x0, y0, width, height)
        map_x, map_y = (gx - x0).astype(np.float32), (gy - y0).astype(np.float32)
        return cv2.remap(ground, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)

    def _noise(self, x0: int, y0: int, width: int, height: int) -> np.ndarray:
        """``(height, width) float32`` grey noise of every octave at level 0 (ground px)."""
        ranges = [(x0, x0 + width, y0, y0 + height)]  # needed [a, b) in x and y at each level
        for _ in OCTAVE_AMPLITUDES:
            ax, bx, ay, by = ranges[-1]
            ranges.append((ax // 2 - MARGIN, -(-bx // 2) + MARGIN, ay // 2 - MARGIN, -(-by // 2) + MARGIN))
        level = np.zeros((1, 1), np.float32)
        origin = (2 * ranges[-1][0], 2 * ranges[-1][2])  # so the first crop below is the top level's range
        for k in range(len(OCTAVE_AMPLITUDES), -1, -1):
            ax, bx, ay, by = ranges[k]
            if k < len(OCTAVE_AMPLITUDES):
                up = cv2.resize(level, (2 * level.shape[1], 2 * level.shape[0]), interpolation=cv2.INTER_CUBIC)
                # cv2.resize puts destination px d at source (d + 0.5) / 2 - 0.5: with origins doubling from
                # level to level, every level's values depend on the global index only.
                level = np.ascontiguousarray(up[ay - origin[1] : by - origin[1], ax - origin[0] : bx - origin[0]])
            else:
                level = np.zeros((by - ay, bx - ax), np.float32)
            if k > 0:
                level += OCTAVE_AMPLITUDES[k - 1] * _uniform(_hash(np.arange(ax, bx), np.arange(ay, by), self.seed, k))
            origin = (2 * ax, 2 * ay)
        return level

    def _fields(self, xs: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Parcel colour ``(len(ys), len(xs), 3) float32`` (grey levels about 0) and the weight
        ``(len(ys), len(xs)) float32`` that is 1 inside a parcel and 0 on a hedge."""
        c, s = math.cos(self.field_angle), math.sin(self.field_angle)
        u = ((c / FIELD_SIZE) * xs).astype(np.float32)[None, :] + ((s / FIELD_SIZE) * ys).astype(np.float32)[:, None]
        v = ((-s / FIELD_SIZE) * xs).astype(np.float32)[None, :] + ((c / FIELD_SIZE) * ys).astype(np.float32)[:, None]
        iu0, iv0 = math.floor(u.min()), math.floor(v.min())
        iu, iv = np.arange(iu0, math.floor(u.max()) + 1), np.arange(iv0, math.floor(v.max()) + 1)
        bits = _hash(iu, iv, self.seed, 100)
        lanes = [_uniform(bits << np.uint32(8 * k)) for k in range(4)]  # four 8-bit lanes in the top bits
        table = np.dstack([FIELD_CONTRAST * lanes[0] + FIELD_TINT * lanes[k] for k in (1, 2, 3)])
        # Each pixel's parcel is floor(u), floor(v): the table looked up by nearest neighbour; the hedge
        # hides where a pixel centre's nearest entry changes.
        map_u, map_v = u - np.float32(iu0 + 0.5), v - np.float32(iv0 + 0.5)
        colour = cv2.remap(table, map_u, map_v, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        edge = np.minimum(np.abs(u - np.rint(u)), np.abs(v - np.rint(v)))
        edge *= np.float32(FIELD_SIZE)
        edge -= np.float32(HEDGE_HALF_WIDTH)
        return colour, np.clip(edge, 0.0, 1.0, out=edge)

    def _roads(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """``(len(ys), len(xs)) float32`` brightness of straight roads, some of a family of parallel lines."""
        c, s = math.cos(self.road_angle), math.sin(self.road_angle)
        w = (c * xs).astype(np.float32)[None, :] + (s * ys).astype(np.float32)[:, None]  # ground px across
        lines = np.arange(math.floor(w.min() / ROAD_SPACING), math.ceil(w.max() / ROAD_SPACING) + 1)
        kept = lines[_uniform(_hash(lines, np.zeros(1, np.int64), self.seed, 101))[0] < 2 * ROAD_FRACTION - 1]
        road = np.zeros(w.shape, np.float32)
        for line in kept:
            dist = np.abs(w - np.float32(line * ROAD_SPACING))
            np.maximum(road, np.clip(ROAD_HALF_WIDTH + 0.5 - dist, 0.0, 1.0), out=road)
        return road * np.float32(ROAD_BRIGHTNESS)


def _hash(i: np.ndarray, j: np.ndarray, seed: int, salt: int) -> np.ndarray:
    """``(len(j), len(i)) uint32`` pseudo-random bits per integer lattice point ``(i, j)``."""
    key = _mix32(
        (i.astype(np.int64) & 0xFFFFFFFF).astype(np.uint32) * np.uint32(0x9E3779B1) + np.uint32(seed & 0xFFFFFFFF)
    )
    row = _mix32(
        (j.astype(np.int64) & 0xFFFFFFFF).astype(np.uint32) * np.uint32(0x85EBCA77)
        + np.uint32(salt * 0x27D4EB2F & 0xFFFFFFFF)
    )
    return _mix32(row[:, None] ^ key[None, :])


def _mix32(key: np.ndarray) -> np.ndarray:
    """Chris Wellons' ``lowbias32`` integer hash, element-wise on ``uint32``."""
    with np.errstate(over="ignore"):
        key = key ^ (key >> np.uint32(16))
        key *= np.uint32(0x7FEB352D)
        key ^= key >> np.uint32(15)
        key *= np.uint32(0x846CA68B)
        key ^= key >> np.uint32(16)
    return key


def _uniform(bits: np.ndarray) -> np.ndarray:
    """``float32`` in ``[-1, 1)`` from the top 24 bits of ``uint32`` ``bits``."""
    return (bits >> np.uint32(8)).astype(np.float32) * np.float32(2.0 / 2**24) - np.float32(1.0)


@dataclass(frozen=True)
class SyntheticStrip:
    """Strip frames on disk plus the truth they were rendered from.

    Attributes
    ----------
    paths : list of Path
        GeoTIFFs in flight order, ``strip_000.tif``, ... (no georeference: it is the pipeline's job).
    gps_path : Path
        CSV side file ``name,lat,lon,alt,accuracy`` with the noisy positions, one row per frame.
    homographies : list of ndarray
        ``(3, 3) float64`` per frame, ``H[2, 2] == 1``: frame px ``(x, y, 1)`` -> ground-plane px.
    frame_size : tuple of int
        ``(width, height)`` px; the width is across track.
    ground_size : tuple of int
        ``(width, height)`` of a ground-plane raster centred on the strip that holds every frame with a
        margin: the extent ``texture_to_utm`` is centred on (the ground itself is unbounded).
    ground : GroundTexture
        The ground the frames show; ``ground.sample(gx, gy)`` evaluates it anywhere.
    epsg : int
        UTM zone of the ground.
    texture_to_utm : ndarray
        ``(3, 3) float64`` affine: ground-plane px -> ``(easting, northing, 1)`` m, north up.
    gsd_m : float
        Metres per ground-plane px.
    gps_true, gps_noisy : list of tuple
        ``(lat, lon, alt_m)`` WGS84 of each frame centre, exact and as written to ``gps_path``.
    gps_noise_m : float
        Standard deviation of the noise added to each of east, north and height, m.
    ccd_gains : ndarray
        ``(ccd_segments,) float64`` gain of each CCD sub-image, left to right; the camera's, same every frame.
    frame_gains : ndarray
        ``(N,) float64`` exposure gain of each frame.
    vignetting : float
        Brightness lost at the frame corners (see the module docstring).
    """

    paths: list[Path]
    gps_path: Path
    homographies: list[np.ndarray]
    frame_size: tuple[int, int]
    ground_size: tuple[int, int]
    ground: GroundTexture
    epsg: int
    texture_to_utm: np.ndarray
    gsd_m: float
    gps_true: list[tuple[float, float, float]]
    gps_noisy: list[tuple[float, float, float]]
    gps_noise_m: float
    ccd_gains: np.ndarray
    frame_gains: np.ndarray
    vignetting: float
    dtype: str = "uint8"

    def frame_center_utm(self, i: int) -> np.ndarray:
        """``(2,) float64`` easting, northing (m) of frame ``i``'s centre pixel."""
        w, h = self.frame_size
        p = self.texture_to_utm @ self.homographies[i] @ np.array([(w - 1) / 2, (h - 1) / 2, 1.0])
        return p[:2] / p[2]

    def corners_ground(self, i: int) -> np.ndarray:
        """``(4, 2) float64`` ground px of frame ``i``'s outer corners (-0.5, -0.5), (w - 0.5, -0.5), ..."""
        w, h = self.frame_size
        corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
        return _apply_homography(self.homographies[i], corners)

    def ccd_seams(self) -> np.ndarray:
        """``(ccd_segments - 1,) float64`` frame ``x`` of the joins between CCD sub-images (pixel edges)."""
        n = len(self.ccd_gains)
        return np.arange(1, n) * self.frame_size[0] / n - 0.5

    def texture_geotransform(self) -> tuple[float, float, float, float, float, float]:
        """``texture_to_utm`` in GDAL's pixel-corner convention: ``rasterio.Affine(*result)``."""
        a = self.texture_to_utm @ _translation(-0.5, -0.5)
        return (a[0, 0], a[0, 1], a[0, 2], a[1, 0], a[1, 1], a[1, 2])

    def render(self, i: int, col0: int, row0: int, width: int, height: int) -> np.ndarray:
        """``(height, width, 3)`` RGB of frame ``i``'s window, in ``dtype``, before any compression."""
        return _render_window(self, i, col0, row0, width, height)


def make_strip(
    out_dir: Path,
    n_frames: int,
    frame_size: tuple[int, int] = FULL_FRAME,
    overlap: float = 0.55,
    gsd_m: float = 0.25,
    altitude_m: float = 8000.0,
    gps_noise_m: float = 1.0,
    ccd_segments: int = 32,
    ccd_step: float = 0.03,
    vignetting: float = 0.1,
    compression: str = "jpeg",
    tiled: bool = True,
    bigtiff: bool = False,
    dtype: str = "uint8",
    seed: int = 0,
    rotation_deg: float = 0.3,
    scale_jitter: float = 0.005,
    perspective: float = 0.002,
    exposure_jitter: float = 0.02,
    origin_latlon: tuple[float, float] = (47.0, 11.0),
    jpeg_quality: int = 90,
    processes: int = 1,
) -> SyntheticStrip:
    """Render a strip of a multi-lens aerial camera into ``out_dir`` and return it with its truth.

    Frame ``i``'s homography is ``H_i = T(c_i) @ R(theta_i) @ S(s_i) @ P_i @ T(-frame_centre)`` as in
    ``scenes.make_flight``, with centres ``c_i`` a north-bound line ``(1 - overlap) * height`` apart.

    Parameters
    ----------
    out_dir : Path
        Folder for ``strip_000.tif``, ... and ``gps.csv``; created if missing.
    n_frames : int
        Number of frames, at least 1.
    frame_size : tuple of int
        ``(width, height)`` px, width across track; the real camera's ``(75000, 1800)`` by default.
    overlap : float
        Forward overlap in [0, 1): fraction of the frame height shared by consecutive frames.
    gsd_m, altitude_m : float
        Metres per ground px, and the flying height written as the GPS altitude.
    gps_noise_m : float
        Standard deviation (m) of Gaussian noise on east, north and height of the written GPS; also the
        CSV's accuracy column.
    ccd_segments, ccd_step : int, float
        The frame is joined from ``ccd_segments`` sub-images across its width, each with a gain uniform
        in ``[1 - ccd_step, 1 + ccd_step]``.
    vignetting : float
        Brightness lost at the corners, in [0, 1).
    compression : {"jpeg", "none"}
        JPEG in TIFF (YCbCr, quality ``jpeg_quality``; uint8 only) or uncompressed.
    tiled : bool
        256 x 256 tiles, or strips of 16 rows (striped JPEG: at most 65500 px wide, GDAL's limit).
    bigtiff : bool
        Write BigTIFF (64-bit offsets) rather than classic TIFF.
    dtype : {"uint8", "uint16"}
        Sample type; uint16 holds the 8-bit scale times 256.
    seed : int
        Seed of everything random: the same arguments give the same pixels (and bytes).
    rotation_deg, scale_jitter, perspective : float
        Bounds of the per-frame jitter: heading in degrees (at most 0.5), scale (at most 0.01), and the
        projective terms ``|p1|, |p2|`` (zero mean over the strip; at most 0.01).
    exposure_jitter : float
        Each frame's gain is uniform in ``[1 - exposure_jitter, 1 + exposure_jitter]``.
    origin_latlon : tuple of float
        WGS84 ``(lat, lon)`` of the ground extent's centre.
    jpeg_quality : int
        GDAL JPEG quality, 1-100.
    processes : int
        Frames rendered at once, each in its own spawned process (one OpenCV thread each); the bytes written
        do not depend on it.

    Returns
    -------
    SyntheticStrip
    """
    _check_strip_args(n_frames, frame_size, overlap, compression, tiled, dtype, rotation_deg, scale_jitter, perspective)
    if not (0 <= vignetting < 1 and 0 <= ccd_step < 0.5 and ccd_segments >= 1 and gps_noise_m >= 0):
        raise ValueError("vignetting must be in [0, 1), ccd_step in [0, 0.5), ccd_segments >= 1, gps_noise_m >= 0")
    if not (0 <= exposure_jitter < 0.5 and 1 <= jpeg_quality <= 100 and processes >= 1):
        raise ValueError("exposure_jitter must be in [0, 0.5), jpeg_quality in [1, 100] and processes >= 1")
    rng = np.random.default_rng(seed)
    local = _strip_homographies(rng, n_frames, frame_size, overlap, rotation_deg, scale_jitter, perspective)
    ground_w, ground_h = _ground_size(local, frame_size)
    to_ground = _translation((ground_w - 1) / 2, (ground_h - 1) / 2)
    homographies = [_normalised(to_ground @ h) for h in local]
    angles = rng.uniform(-math.pi / 4, math.pi / 4, 2)
    ground = GroundTexture(int(rng.integers(2**31)), float(angles[0]), float(angles[1] + math.pi / 2))
    epsg, texture_to_utm = _georeference(origin_latlon, gsd_m, ground_w, ground_h)
    ccd_gains = rng.uniform(1 - ccd_step, 1 + ccd_step, ccd_segments)
    frame_gains = rng.uniform(1 - exposure_jitter, 1 + exposure_jitter, n_frames)
    noise = rng.standard_normal((n_frames, 3)) * gps_noise_m
    out_dir = Path(out_dir)
    strip = SyntheticStrip(
        paths=[out_dir / f"strip_{i:03d}.tif" for i in range(n_frames)],
        gps_path=out_dir / GPS_FILE,
        homographies=homographies,
        frame_size=frame_size,
        ground_size=(ground_w, ground_h),
        ground=ground,
        epsg=epsg,
        texture_to_utm=texture_to_utm,
        gsd_m=gsd_m,
        gps_true=[],
        gps_noisy=[],
        gps_noise_m=gps_noise_m,
        ccd_gains=ccd_gains,
        frame_gains=frame_gains,
        vignetting=vignetting,
        dtype=dtype,
    )
    strip = _with_gps(strip, altitude_m, noise)
    out_dir.mkdir(parents=True, exist_ok=True)
    frame_args = [(strip, i, compression, tiled, bigtiff, jpeg_quality) for i in range(n_frames)]
    if processes == 1 or n_frames == 1:
        for args in frame_args:
            _write_frame(*args)
    else:
        context = multiprocessing.get_context("spawn")  # no fork of a process holding GDAL and OpenCV threads
        workers = min(processes, n_frames)
        with ProcessPoolExecutor(workers, context, initializer=cv2.setNumThreads, initargs=(1,)) as pool:
            for _ in pool.map(_write_frame, *zip(*frame_args, strict=True)):
                pass  # a frame that failed raises here
    _write_gps_csv(strip)
    return strip


def _check_strip_args(
    n_frames: int,
    frame_size: tuple[int, int],
    overlap: float,
    compression: str,
    tiled: bool,
    dtype: str,
    rotation_deg: float,
    scale_jitter: float,
    perspective: float,
) -> None:
    if n_frames < 1:
        raise ValueError(f"a strip needs at least one frame, got {n_frames}")
    if min(frame_size) < 16:
        raise ValueError(f"frames must be at least 16x16 px, got {frame_size}")
    if not 0 <= overlap < 1:
        raise ValueError(f"overlap must be in [0, 1), got {overlap}")
    if compression not in ("jpeg", "none"):
        raise ValueError(f"compression must be 'jpeg' or 'none', got {compression!r}")
    if dtype not in ("uint8", "uint16"):
        raise ValueError(f"dtype must be 'uint8' or 'uint16', got {dtype!r}")
    if compression == "jpeg" and dtype != "uint8":
        # The camera's JPEG frames are 8-bit, and 12-bit JPEG in TIFF did not round-trip with this GDAL.
        raise ValueError("JPEG in TIFF frames are 8-bit: use dtype='uint8' or compression='none'")
    if compression == "jpeg" and not tiled and frame_size[0] > JPEG_MAX_SIDE:
        # A JPEG strip is one JPEG image as wide as the frame, and JPEG sizes are 16-bit.
        raise ValueError(f"striped JPEG frames are at most {JPEG_MAX_SIDE} px wide: use tiled=True")
    if not (0 <= rotation_deg <= 0.5 and 0 <= scale_jitter <= 0.01 and 0 <= perspective <= 0.01):
        raise ValueError("rotation_deg must be in [0, 0.5], scale_jitter in [0, 0.01], perspective in [0, 0.01]")


def _strip_homographies(
    rng: np.random.Generator,
    n_frames: int,
    frame_size: tuple[int, int],
    overlap: float,
    rotation_deg: float,
    scale_jitter: float,
    perspective: float,
) -> list[np.ndarray]:
    """``(3, 3) float64`` frame px -> ground px relative to the strip's centre, in flight order."""
    w, h = frame_size
    step = (1 - overlap) * h
    # North-bound: frame i + 1 is ``step`` px north (smaller ground y) of frame i.
    ys = -(np.arange(n_frames) - (n_frames - 1) / 2) * step
    thetas = np.deg2rad(rng.uniform(-rotation_deg, rotation_deg, n_frames))
    scales = rng.uniform(1 - scale_jitter, 1 + scale_jitter, n_frames)
    tilts = _perspective_terms(rng, n_frames, perspective)
    to_centre = _translation(-(w - 1) / 2, -(h - 1) / 2)
    result = []
    for cy, theta, s, (p1, p2) in zip(ys, thetas, scales, tilts, strict=True):
        c, si = math.cos(theta), math.sin(theta)
        rotate_scale = np.array([[s * c, -s * si, 0], [s * si, s * c, 0], [0, 0, 1]])
        tilt = np.array([[1, 0, 0], [0, 1, 0], [p1 / w, p2 / h, 1]])
        result.append(_translation(0.0, cy) @ rotate_scale @ tilt @ to_centre)
    return result


def adjustment_inputs(
    seed: int,
    n_frames: int,
    frame_size: tuple[int, int],
    overlap: float,
    gsd_m: float,
    *,
    gap: int = 1,
    ties_per_pair: int = 400,
    tie_noise_px: float = 0.1,
    gps_noise_m: float = 1.0,
) -> tuple[list[Any], dict[int, Any], dict[tuple[int, int], Any], dict[int, np.ndarray]]:
    """What align_frames' plane adjustment gets from a strip, drawn without rendering a pixel: the true frame
    -> ground px homographies (those of :func:`make_strip`), the frames with GPS fixes of their centres (Gaussian
    noise, ``gps_accuracy_m`` the noise), tie points between each frame and the next ``gap`` frames sharing at
    least 10 % of a frame (``ties_per_pair`` spread over the overlap, Gaussian noise), and the start chained
    from the middle frame through consecutive pairs. Ground px are ``gsd_m`` m (UTM zone 32N)."""
    from workers.algorithms.mosaic import TiePoints, apply_homography, chain_homographies
    from workers.records import Frame

    rng = np.random.default_rng(seed)
    w, h = frame_size
    truth = _strip_homographies(rng, n_frames, frame_size, overlap, 0.3, 0.005, 0.002)
    ties, pairwise = {}, {}
    for i in range(n_frames):
        for j in range(i + 1, min(n_frames, i + gap + 1)):
            shared = overlap - (j - i - 1) * (1 - overlap)  # frame i's top rows are frame j's bottom rows
            if shared < 0.1:
                continue
            points = np.column_stack(
                [rng.uniform(0, w - 1, ties_per_pair), rng.uniform(0, (shared - 0.02) * h, ties_per_pair)]
            )
            seen = apply_homography(np.linalg.inv(truth[j]) @ truth[i], points) + rng.normal(
                0, tie_noise_px, points.shape
            )
            ties[(i, j)] = TiePoints(points, seen)
            if j == i + 1:
                pairwise[(i, j)] = cv2.findHomography(points, seen, 0)[0]
    to_wgs84 = Transformer.from_crs(32632, 4326, always_xy=True)
    frames = {}
    for k in range(n_frames):
        gx, gy = apply_homography(truth[k], [[(w - 1) / 2, (h - 1) / 2]])[0] + rng.normal(0, gps_noise_m / gsd_m, 2)
        lon, lat = to_wgs84.transform(650_000 + gsd_m * gx, 5_200_000 - gsd_m * gy)
        gps = {"lat": lat, "lon": lon, "alt": 8000.0}
        frames[k] = Frame(k, f"strip_{k:05d}.tif", "", w, h, w, h, 1.0, gps=gps, gps_accuracy_m=gps_noise_m)
    root = n_frames // 2
    parent = {k: k + 1 if k < root else k - 1 for k in range(n_frames) if k != root}
    return truth, frames, ties, chain_homographies(root, parent, pairwise)


def _ground_size(local: list[np.ndarray], frame_size: tuple[int, int]) -> tuple[int, int]:
    """``(width, height)`` of a ground raster centred on the strip holding every frame with a margin."""
    w, h = frame_size
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    reach = np.abs(np.vstack([_apply_homography(hom, corners) for hom in local])).max(axis=0)
    half = np.ceil(reach + 0.05 * h)
    return int(2 * half[0] + 1), int(2 * half[1] + 1)


def _with_gps(strip: SyntheticStrip, altitude_m: float, noise: np.ndarray) -> SyntheticStrip:
    """``strip`` with its true and noisy GPS; ``noise`` is ``(N, 3)`` east, north, up metres."""
    to_wgs84 = Transformer.from_crs(strip.epsg, 4326, always_xy=True)
    true, noisy = [], []
    for i, (de, dn, du) in enumerate(noise):
        east, north = strip.frame_center_utm(i)
        lon, lat = to_wgs84.transform(east, north)
        true.append((float(lat), float(lon), float(altitude_m)))
        lon, lat = to_wgs84.transform(east + de, north + dn)
        noisy.append((float(lat), float(lon), float(altitude_m + du)))
    return dataclasses.replace(strip, gps_true=true, gps_noisy=noisy)


def _write_gps_csv(strip: SyntheticStrip) -> None:
    with strip.gps_path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["name", "lat", "lon", "alt", "accuracy"])
        for path, (lat, lon, alt) in zip(strip.paths, strip.gps_noisy, strict=True):
            writer.writerow([path.name, f"{lat:.9f}", f"{lon:.9f}", f"{alt:.3f}", f"{strip.gps_noise_m:g}"])


def _render_window(strip: SyntheticStrip, i: int, col0: int, row0: int, width: int, height: int) -> np.ndarray:
    """``(height, width, 3)`` RGB in ``strip.dtype`` of frame ``i``, rendered ``RENDER_COLUMNS`` at a time.

    Each block is the bicubic resampling of the ground raster under it (``cv2.warpPerspective`` of
    ``GroundTexture.raster``), the same values ``GroundTexture.sample`` gives at the mapped pixel centres.
    """
    out = np.empty((height, width, 3), strip.dtype)
    hom = strip.homographies[i]
    ys = np.arange(row0, row0 + height, dtype=np.float64)
    for c in range(0, width, RENDER_COLUMNS):
        cw = min(RENDER_COLUMNS, width - c)
        corners = np.array(
            [
                [col0 + c, row0],
                [col0 + c + cw - 1, row0],
                [col0 + c, row0 + height - 1],
                [col0 + c + cw - 1, row0 + height - 1],
            ],
            np.float64,
        )
        ground = _apply_homography(hom, corners)
        x0, y0 = np.floor(ground.min(axis=0)).astype(int) - MARGIN
        x1, y1 = np.ceil(ground.max(axis=0)).astype(int) + MARGIN + 1
        raster = strip.ground.raster(int(x0), int(y0), int(x1 - x0), int(y1 - y0))
        block_to_raster = _translation(-float(x0), -float(y0)) @ hom @ _translation(col0 + c, row0)
        flags = cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP
        rgb = cv2.warpPerspective(raster, block_to_raster, (cw, height), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        xs = np.arange(col0 + c, col0 + c + cw, dtype=np.float64)
        rgb *= _radiometry(strip, i, xs, ys)[..., None]
        out[:, c : c + cw] = _quantise(rgb, strip.dtype)
    return out


def _radiometry(strip: SyntheticStrip, i: int, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """``(len(ys), len(xs)) float32`` gain: frame exposure x CCD sub-image x vignetting, at frame px."""
    w, h = strip.frame_size
    n = len(strip.ccd_gains)
    segment = np.minimum(((xs + 0.5) * n / w).astype(np.int64), n - 1)
    u = (xs - (w - 1) / 2) / (w / 2)
    v = (ys - (h - 1) / 2) / (h / 2)
    row = (strip.frame_gains[i] * strip.ccd_gains[segment]).astype(np.float32)
    vignette = (1 - strip.vignetting * u**2 / 2).astype(np.float32)[None, :] - (strip.vignetting * v**2 / 2).astype(
        np.float32
    )[:, None]
    vignette *= row[None, :]
    return vignette


def _quantise(rgb: np.ndarray, dtype: str) -> np.ndarray:
    """Round ``float32`` 8-bit grey levels to ``dtype`` (uint16: times 256), in place on ``rgb``."""
    if dtype == "uint16":
        rgb *= np.float32(256)
    top = 255 if dtype == "uint8" else 65535
    np.clip(np.rint(rgb, out=rgb), 0, top, out=rgb)
    return rgb.astype(dtype)


def _write_frame(strip: SyntheticStrip, i: int, compression: str, tiled: bool, bigtiff: bool, quality: int) -> None:
    """Render frame ``i`` window by window into ``strip.paths[i]``, each write filling whole file blocks."""
    w, h = strip.frame_size
    profile: dict[str, object] = {
        "driver": "GTiff",
        "width": w,
        "height": h,
        "count": 3,
        "dtype": strip.dtype,
        "interleave": "pixel",
        "BIGTIFF": "YES" if bigtiff else "NO",
    }
    if tiled:
        profile.update(tiled=True, blockxsize=TILE, blockysize=TILE)
    else:
        profile.update(tiled=False, blockysize=STRIP_ROWS)
    if compression == "jpeg":
        profile.update(compress="JPEG", photometric="YCbCr", JPEG_QUALITY=quality)
    else:
        profile.update(compress="NONE", photometric="RGB")
    tmp = strip.paths[i].with_suffix(".tif.part")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)  # raw frames carry no georeference
            with rasterio.open(tmp, "w", **profile) as dst:
                for window in _write_windows(w, h, tiled):
                    rgb = _render_window(strip, i, window.col_off, window.row_off, window.width, window.height)
                    dst.write(np.moveaxis(rgb, 2, 0), window=window)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    tmp.replace(strip.paths[i])


def _write_windows(width: int, height: int, tiled: bool) -> Iterator[Window]:
    """Windows covering a frame, each a run of whole file blocks, so GDAL never re-reads a block.

    Tiled: full-height columns ``RENDER_COLUMNS`` wide (whole tile columns). Striped: full-width bands of
    whole strips, about ``BAND_PIXELS`` each (a strip spans the width, so columns would leave every strip
    half written).
    """
    if tiled:
        for c in range(0, width, RENDER_COLUMNS):
            yield Window(c, 0, min(RENDER_COLUMNS, width - c), height)
        return
    rows = max(STRIP_ROWS, BAND_PIXELS // width // STRIP_ROWS * STRIP_ROWS)
    for r in range(0, height, rows):
        yield Window(0, r, width, min(rows, height - r))
