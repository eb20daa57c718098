"""Synthetic drone flights with known ground truth, for unit, end-to-end and browser tests.

A flight is a set of JPEG frames cut from one large random texture by known homographies, with EXIF
GPS computed from a known north-up UTM georeference of that texture. A mosaicking pipeline run on the
frames should recover the homographies up to one common transform, and the georeference up to GPS
error.

Pixel convention: OpenCV's, as used by ``cv2.warpPerspective``: integer ``(x, y)`` is the centre of
pixel ``[y, x]``, so an image of width ``w`` spans ``x`` in ``[-0.5, w - 0.5]`` and its centre pixel
is ``((w - 1) / 2, (h - 1) / 2)``. ``SyntheticFlight.texture_geotransform`` gives the GDAL/rasterio
(pixel-corner) version of ``texture_to_utm``.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import io
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, TiffImagePlugin
from pyproj import Transformer

GPS_IFD = 0x8825
EXIF_IFD = 0x8769
SIDE_OVERLAP = 0.3  # "grid" layout: fraction of frame height shared by the two flight lines
FIRST_SHOT = dt.datetime(2024, 6, 1, 10, 0, 0)
SHOT_INTERVAL = dt.timedelta(seconds=2)
BOMB_SIDE = 50_000


@dataclass(frozen=True)
class SyntheticFlight:
    """Frames on disk plus the truth they were rendered from.

    Attributes
    ----------
    paths : list of Path
        JPEG files in flight order, ``frame_000.jpg``, ``frame_001.jpg``, ...
    homographies : list of ndarray
        ``(3, 3) float64`` per frame, normalised to ``H[2, 2] == 1``: frame pixel ``(x, y, 1)`` ->
        texture pixel ``(x, y, 1)``; ``frame = cv2.warpPerspective(texture, inv(H), frame_size)``.
    frame_size : tuple of int
        ``(width, height)`` of every frame, px.
    texture : ndarray
        ``(H, W, 3) uint8`` BGR, the ground the frames were cut from.
    epsg : int
        EPSG code of the UTM zone of the ground, e.g. 32615.
    texture_to_utm : ndarray
        ``(3, 3) float64`` affine: texture pixel ``(x, y, 1)`` -> ``(easting, northing, 1)``, metres;
        north up, so ``y`` grows southwards.
    gsd_m : float
        Metres per texture pixel.
    gps : list of tuple or None
        ``(lat, lon, alt_m)`` written to each frame's EXIF (WGS84 degrees), or None if no GPS.
    """

    paths: list[Path]
    homographies: list[np.ndarray]
    frame_size: tuple[int, int]
    texture: np.ndarray
    epsg: int
    texture_to_utm: np.ndarray
    gsd_m: float
    gps: list[tuple[float, float, float]] | None

    def frame_center_utm(self, i: int) -> np.ndarray:
        """``(2,) float64`` easting, northing (m) of frame ``i``'s centre pixel."""
        w, h = self.frame_size
        p = self.texture_to_utm @ self.homographies[i] @ np.array([(w - 1) / 2, (h - 1) / 2, 1.0])
        return p[:2] / p[2]

    def corners_texture(self, i: int) -> np.ndarray:
        """``(4, 2) float64`` texture px of frame ``i``'s corners (0, 0), (w, 0), (w, h), (0, h)."""
        w, h = self.frame_size
        corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)
        return _apply_homography(self.homographies[i], corners)

    def texture_geotransform(self) -> tuple[float, float, float, float, float, float]:
        """``texture_to_utm`` in the pixel-corner convention of GDAL: ``rasterio.Affine(*result)``."""
        # GDAL puts pixel [0, 0]'s outer corner at (0, 0); OpenCV puts its centre there.
        a = self.texture_to_utm @ np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]], np.float64)
        return (a[0, 0], a[0, 1], a[0, 2], a[1, 0], a[1, 1], a[1, 2])


def make_texture(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A random, non-periodic ground texture rich in detail at every scale.

    Band-limited noise at several scales, a few thousand filled shapes and lines of random colours,
    and fine grain on top, so that SIFT finds thousands of distinctive keypoints everywhere and no
    patch looks like another.

    Parameters
    ----------
    height, width : int
        Size in px, each at least 16.
    seed : int
        Seed of ``numpy.random.default_rng``; the same seed gives the same texture.

    Returns
    -------
    ndarray
        ``(height, width, 3) uint8`` BGR.
    """
    if height < 16 or width < 16:
        raise ValueError(f"texture must be at least 16x16 px, got {width}x{height}")
    rng = np.random.default_rng(seed)
    grey = 128 + 40 * _band_limited_noise(rng, height, width, 160, 1)
    grey += 25 * _band_limited_noise(rng, height, width, 40, 1)
    tint = 18 * _band_limited_noise(rng, height, width, 240, 3)  # slow colour drift, like soil vs grass
    img = np.clip(grey + tint, 0, 255).astype(np.uint8)
    _draw_shapes(img, rng, count=height * width // 700)
    # Fine grain after the shapes, so that their insides have texture too.
    grain = 14 * _band_limited_noise(rng, height, width, 3, 1)
    grain = grain + 6 * _band_limited_noise(rng, height, width, 8, 3)  # (H, W, 1) + (H, W, 3)
    return np.clip(img + grain, 0, 255).astype(np.uint8)


def _band_limited_noise(rng: np.random.Generator, height: int, width: int, cell: int, channels: int) -> np.ndarray:
    """``(height, width, channels) float32`` noise with unit-ish amplitude and features ``cell`` px wide."""
    gh, gw = height // cell + 4, width // cell + 4
    coarse = rng.standard_normal((gh, gw, channels)).astype(np.float32)
    fine = cv2.resize(coarse, (gw * cell, gh * cell), interpolation=cv2.INTER_CUBIC)
    # Skip the first cells: bicubic interpolation is one-sided at the border.
    return fine.reshape(gh * cell, gw * cell, channels)[cell : cell + height, cell : cell + width]


def _draw_shapes(img: np.ndarray, rng: np.random.Generator, count: int) -> None:
    """Draw ``count`` random filled circles, ellipses, polygons and lines on ``img`` in place."""
    h, w = img.shape[:2]
    centres = rng.uniform((0, 0), (w, h), size=(count, 2)).astype(int)
    sizes = np.exp(rng.uniform(np.log(3), np.log(45), count))  # log-uniform: detail at every scale
    kinds = rng.integers(0, 4, count)
    colours = rng.integers(0, 256, (count, 3))
    angles = rng.uniform(0, 360, count)
    for (cx, cy), r, kind, colour, angle in zip(centres, sizes, kinds, colours.tolist(), angles, strict=True):
        radius = max(int(r), 2)
        if kind == 0:
            cv2.circle(img, (int(cx), int(cy)), radius, colour, -1, cv2.LINE_AA)
        elif kind == 1:
            axes = (radius, max(radius // 3, 1))
            cv2.ellipse(img, (int(cx), int(cy)), axes, float(angle), 0, 360, colour, -1, cv2.LINE_AA)
        elif kind == 2:
            pts = (np.array([cx, cy]) + rng.uniform(-r, r, (int(rng.integers(3, 7)), 2))).astype(np.int32)
            cv2.fillPoly(img, [pts], colour, cv2.LINE_AA)
        else:
            rad = math.radians(angle)
            end = (int(cx + 2 * r * math.cos(rad)), int(cy + 2 * r * math.sin(rad)))
            cv2.line(img, (int(cx), int(cy)), end, colour, int(rng.integers(1, 4)), cv2.LINE_AA)


def make_flight(
    out_dir: Path,
    n_frames: int = 8,
    frame_size: tuple[int, int] = (640, 480),
    layout: str = "strip",
    overlap: float = 0.6,
    rotation_deg: float = 8.0,
    scale_jitter: float = 0.05,
    perspective: float = 0.0,
    gps: bool = True,
    seed: int = 0,
    origin_latlon: tuple[float, float] = (29.7600, -95.3700),
    gsd_m: float = 0.05,
    altitude_m: float = 60.0,
    focal_length_mm: float = 8.8,
    jpeg_quality: int = 92,
) -> SyntheticFlight:
    """Render a synthetic drone flight into ``out_dir`` and return it with its ground truth.

    Frame ``i`` is ``cv2.warpPerspective(texture, inv(H_i), frame_size, flags=cv2.INTER_LINEAR)`` with
    ``H_i = T(centre_i) @ R(theta_i) @ S(s_i) @ P_i @ T(-frame_centre)``, ``P_i`` the projective matrix
    ``[[1, 0, 0], [0, 1, 0], [p1 / w, p2 / h, 1]]``.

    Parameters
    ----------
    out_dir : Path
        Folder for ``frame_000.jpg``, ...; created if missing.
    n_frames : int
        Number of frames (at least 2 for ``"grid"``).
    frame_size : tuple of int
        ``(width, height)`` px.
    layout : {"strip", "grid"}
        ``"strip"``: one west-to-east line. ``"grid"``: two lines flown serpentine (east, then back
        west, heading unchanged) sharing ``SIDE_OVERLAP`` of the frame height; the first
        ``ceil(n / 2)`` frames are on the northern line.
    overlap : float
        Forward overlap in [0, 1): fraction of the frame width shared by consecutive frames of a line
        before rotation and scale jitter.
    rotation_deg : float
        ``theta_i`` is uniform in ``[-rotation_deg, rotation_deg]`` degrees.
    scale_jitter : float
        ``s_i`` (texture px per frame px) is uniform in ``[1 - scale_jitter, 1 + scale_jitter]``.
    perspective : float
        Bound on ``|p1|, |p2|``, which have zero mean over the flight; 0.02 moves corners ~1 %.
        0 gives pure similarities, a nadir flight.
    gps : bool
        Write GPS EXIF (``flight.gps`` is None otherwise; focal length is written either way).
    seed : int
        Seed of everything random: the same arguments give byte-identical files.
    origin_latlon : tuple of float
        WGS84 ``(lat, lon)`` of the texture centre; its UTM zone is the flight's ``epsg``.
    gsd_m, altitude_m, focal_length_mm : float
        Metres per texture px, flying height for GPSAltitude, and EXIF FocalLength. The EXIF sensor
        size (FocalPlaneXResolution, FocalLengthIn35mmFilm) is chosen so that
        ``gsd = altitude * pixel_pitch / focal`` holds at scale 1.
    jpeg_quality : int
        Pillow JPEG quality, 1-95.

    Returns
    -------
    SyntheticFlight
    """
    _check_flight_args(n_frames, frame_size, layout, overlap, scale_jitter, perspective)
    rng = np.random.default_rng(seed)
    centres = _layout_centres(layout, n_frames, frame_size, overlap)
    local = _frame_homographies(rng, centres, frame_size, rotation_deg, scale_jitter, perspective)
    tex_w, tex_h = _texture_size(local, frame_size)
    to_texture = _translation((tex_w - 1) / 2, (tex_h - 1) / 2)
    homographies = [_normalised(to_texture @ h) for h in local]
    texture = make_texture(tex_h, tex_w, seed=int(rng.integers(2**31)))
    epsg, texture_to_utm = _georeference(origin_latlon, gsd_m, tex_w, tex_h)
    flight = SyntheticFlight(
        paths=[Path(out_dir) / f"frame_{i:03d}.jpg" for i in range(n_frames)],
        homographies=homographies,
        frame_size=frame_size,
        texture=texture,
        epsg=epsg,
        texture_to_utm=texture_to_utm,
        gsd_m=gsd_m,
        gps=None,
    )
    if gps:
        flight = _with_gps(flight, altitude_m)
    _write_frames(flight, focal_length_mm, altitude_m, jpeg_quality)
    return flight


CAR_SIZE = (48, 24)  # (length, width) of the moving car, texture px
CAR_BGR = (30, 30, 220)  # saturated red: no part of the texture is as red over the car's area


@dataclass(frozen=True)
class SeamFlight:
    """A flight whose frames disagree where they overlap, as real ones do, with the truth of each disagreement.

    Attributes
    ----------
    flight : SyntheticFlight
        The frames (rewritten with the effects below) and their geometry.
    gains : ndarray
        ``(N,) float64`` exposure of each frame (its pixels are the texture's times this).
    vignette : tuple of float
        ``(c1, c2)`` of the lens fall-off ``exp(c1 rho^2 + c2 rho^4)`` every frame carries
        (``workers.algorithms.mosaic.vignetting``'s model, rho 1 at a frame's corners).
    cars : ndarray
        ``(N, 4, 2) float64``: texture px of the corners of the car in frame ``i``'s shot; it drives on, so each
        frame sees it somewhere else, and the frames that overlap there see the bare ground.
    """

    flight: SyntheticFlight
    gains: np.ndarray
    vignette: tuple[float, float]
    cars: np.ndarray

    def car_colour(self) -> np.ndarray:
        """``(3,) float64`` the car's BGR before gain and fall-off."""
        return np.array(CAR_BGR, np.float64)


def make_seam_flight(
    out_dir: Path,
    n_frames: int = 6,
    exposure: float = 0.2,
    vignette: tuple[float, float] = (-0.35, -0.05),
    seed: int = 4,
    **flight_args: object,
) -> SeamFlight:
    """:func:`make_flight` (GPS, a strip by default) with per-frame exposure, a lens fall-off and a moving car.

    Frame ``i`` is rendered from the texture with the car drawn at ``cars[i]`` (a point ahead of and below the
    frame's centre, so in the overlap with the frame before it), then multiplied by ``gains[i]`` (uniform in
    ``[1 - exposure, 1 + exposure]``) and the fall-off, and written as :func:`make_flight` writes it.
    """
    flight = make_flight(out_dir, n_frames=n_frames, gps=True, seed=seed, **flight_args)  # type: ignore[arg-type]
    rng = np.random.default_rng(seed + 1)
    gains = rng.uniform(1 - exposure, 1 + exposure, n_frames)
    w, h = flight.frame_size
    length, width = CAR_SIZE
    body = np.array([[-length, -width], [length, -width], [length, width], [-length, width]], np.float64) / 2
    cars = []
    for i in range(n_frames):
        centre = _apply_homography(flight.homographies[i], np.array([[0.3 * w, 0.62 * h]]))[0]
        cars.append(centre + body)
    seam_flight = SeamFlight(flight=flight, gains=gains, vignette=vignette, cars=np.array(cars))
    _write_frames(flight, 8.8, 60.0, 92, render=partial(_seam_frame, seam_flight))
    return seam_flight


def _seam_frame(seam_flight: SeamFlight, i: int) -> np.ndarray:
    """``(h, w, 3) uint8`` frame ``i`` of a :class:`SeamFlight`: the car on the ground, exposure, fall-off."""
    flight = seam_flight.flight
    w, h = flight.frame_size
    ground = flight.texture.copy()
    cv2.fillPoly(ground, [np.round(seam_flight.cars[i]).astype(np.int32)], CAR_BGR, cv2.LINE_AA)
    frame = cv2.warpPerspective(ground, np.linalg.inv(flight.homographies[i]), (w, h), flags=cv2.INTER_LINEAR)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    cx, cy = (w - 1) / 2, (h - 1) / 2
    rho2 = ((xs - cx) ** 2 + (ys - cy) ** 2) / (cx * cx + cy * cy)
    c1, c2 = seam_flight.vignette
    scale = seam_flight.gains[i] * np.exp(c1 * rho2 + c2 * rho2 * rho2)
    return np.clip(frame * scale[..., None] + 0.5, 0, 255).astype(np.uint8)


def _check_flight_args(
    n_frames: int,
    frame_size: tuple[int, int],
    layout: str,
    overlap: float,
    scale_jitter: float,
    perspective: float,
) -> None:
    if layout not in ("strip", "grid"):
        raise ValueError(f"layout must be 'strip' or 'grid', got {layout!r}")
    if n_frames < (2 if layout == "grid" else 1):
        raise ValueError(f"a {layout} layout needs more frames than {n_frames}")
    if min(frame_size) < 16:
        raise ValueError(f"frames must be at least 16x16 px, got {frame_size}")
    if not 0 <= overlap < 1:
        raise ValueError(f"overlap must be in [0, 1), got {overlap}")
    if not 0 <= scale_jitter < 0.5:
        raise ValueError(f"scale_jitter must be in [0, 0.5), got {scale_jitter}")
    if not 0 <= perspective <= 0.5:  # beyond 0.5 a frame corner could reach the horizon
        raise ValueError(f"perspective must be in [0, 0.5], got {perspective}")


def _layout_centres(layout: str, n_frames: int, frame_size: tuple[int, int], overlap: float) -> np.ndarray:
    """``(N, 2) float64`` frame centres, texture px relative to the layout's centre, in flight order."""
    w, h = frame_size
    step = (1 - overlap) * w
    if layout == "strip":
        xs = (np.arange(n_frames) - (n_frames - 1) / 2) * step
        return np.column_stack([xs, np.zeros(n_frames)])
    first = math.ceil(n_frames / 2)
    along = (np.arange(first) - (first - 1) / 2) * step
    row_gap = (1 - SIDE_OVERLAP) * h
    north = np.column_stack([along, np.full(first, -row_gap / 2)])
    # Serpentine: the second line is flown back west, starting above the last frame of the first.
    south = np.column_stack([along[::-1], np.full(first, row_gap / 2)])[: n_frames - first]
    return np.vstack([north, south])


def _frame_homographies(
    rng: np.random.Generator,
    centres: np.ndarray,
    frame_size: tuple[int, int],
    rotation_deg: float,
    scale_jitter: float,
    perspective: float,
) -> list[np.ndarray]:
    """``(3, 3) float64`` frame px -> layout px per centre of ``centres`` ``(N, 2)``."""
    w, h = frame_size
    n = len(centres)
    thetas = np.deg2rad(rng.uniform(-rotation_deg, rotation_deg, n))
    scales = rng.uniform(1 - scale_jitter, 1 + scale_jitter, n)
    tilts = _perspective_terms(rng, n, perspective)
    to_centre = _translation(-(w - 1) / 2, -(h - 1) / 2)
    result = []
    for (cx, cy), theta, s, (p1, p2) in zip(centres, thetas, scales, tilts, strict=True):
        c, si = math.cos(theta), math.sin(theta)
        rotate_scale = np.array([[s * c, -s * si, 0], [s * si, s * c, 0], [0, 0, 1]])
        tilt = np.array([[1, 0, 0], [0, 1, 0], [p1 / w, p2 / h, 1]])
        result.append(_translation(cx, cy) @ rotate_scale @ tilt @ to_centre)
    return result


def _perspective_terms(rng: np.random.Generator, n: int, bound: float) -> np.ndarray:
    """``(n, 2) float64`` ``(p1, p2)`` with zero mean over frames and ``|p| <= bound``."""
    terms = rng.uniform(-bound, bound, (n, 2))
    terms -= terms.mean(axis=0)  # no systematic tilt of the whole flight
    peak = np.abs(terms).max(initial=0.0)
    # Removing the mean can push a term past the bound; a common scale keeps the mean at zero.
    return terms * (bound / peak) if peak > bound else terms


def _texture_size(local: list[np.ndarray], frame_size: tuple[int, int]) -> tuple[int, int]:
    """``(width, height)`` of a texture centred on the layout that holds every frame with a margin."""
    w, h = frame_size
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    reach = np.abs(np.vstack([_apply_homography(hom, corners) for hom in local])).max(axis=0)
    margin = 0.1 * max(w, h)
    # Symmetric about the layout centre so that the texture centre is the layout centre.
    half = np.ceil(reach + margin)
    return int(2 * half[0] + 1), int(2 * half[1] + 1)


def _georeference(origin_latlon: tuple[float, float], gsd_m: float, width: int, height: int) -> tuple[int, np.ndarray]:
    """UTM EPSG code and ``(3, 3)`` texture px -> UTM affine putting the texture centre at the origin."""
    lat, lon = origin_latlon
    zone = int((lon + 180) // 6) % 60 + 1
    epsg = (32600 if lat >= 0 else 32700) + zone
    east, north = Transformer.from_crs(4326, epsg, always_xy=True).transform(lon, lat)
    cx, cy = (width - 1) / 2, (height - 1) / 2
    affine = np.array([[gsd_m, 0, east - gsd_m * cx], [0, -gsd_m, north + gsd_m * cy], [0, 0, 1]], np.float64)
    return epsg, affine


def _with_gps(flight: SyntheticFlight, altitude_m: float) -> SyntheticFlight:
    """``flight`` with ``gps`` set to the WGS84 position of each frame centre at ``altitude_m``."""
    to_wgs84 = Transformer.from_crs(flight.epsg, 4326, always_xy=True)
    positions = []
    for i in range(len(flight.paths)):
        east, north = flight.frame_center_utm(i)
        lon, lat = to_wgs84.transform(east, north)
        positions.append((float(lat), float(lon), float(altitude_m)))
    return dataclasses.replace(flight, gps=positions)


def _write_frames(
    flight: SyntheticFlight,
    focal_length_mm: float,
    altitude_m: float,
    quality: int,
    render: Callable[[int], np.ndarray] | None = None,
) -> None:
    """Render every frame of ``flight`` (by ``render(i)`` when given) and save it as a JPEG with EXIF."""
    w, h = flight.frame_size
    pixel_pitch_mm = flight.gsd_m * focal_length_mm / altitude_m
    for i, path in enumerate(flight.paths):
        if render is not None:
            frame = render(i)
        else:
            frame = cv2.warpPerspective(
                flight.texture, np.linalg.inv(flight.homographies[i]), (w, h), flags=cv2.INTER_LINEAR
            )
        exif = _exif_bytes(
            gps=flight.gps[i] if flight.gps is not None else None,
            focal_length_mm=focal_length_mm,
            sensor_width_mm=pixel_pitch_mm * w,
            pixels_per_cm=10.0 / pixel_pitch_mm,
            taken=FIRST_SHOT + i * SHOT_INTERVAL,
        )
        path.parent.mkdir(parents=True, exist_ok=True)
        rgb = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        Image.fromarray(rgb).save(path, "JPEG", quality=quality, exif=exif)


def _exif_bytes(
    gps: tuple[float, float, float] | None,
    focal_length_mm: float,
    sensor_width_mm: float,
    pixels_per_cm: float,
    taken: dt.datetime,
) -> bytes:
    """EXIF block (TIFF structure, no ``Exif\\0\\0`` header) for one frame, built with Pillow."""
    exif = Image.Exif()
    stamp = taken.strftime("%Y:%m:%d %H:%M:%S")
    exif[0x010F] = "Fotoskhema"  # Make
    exif[0x0110] = "Synthetic"  # Model
    exif[0x0132] = stamp  # DateTime
    sub = exif.get_ifd(EXIF_IFD)
    sub[0x9003] = stamp  # DateTimeOriginal
    sub[0x920A] = _rational(focal_length_mm, 1000)  # FocalLength, mm
    # OpenSfM's convention: a 35 mm frame is 36 mm wide along the image's long side.
    sub[0xA405] = max(1, round(focal_length_mm * 36.0 / sensor_width_mm))  # FocalLengthIn35mmFilm
    sub[0xA20E] = _rational(pixels_per_cm, 1000)  # FocalPlaneXResolution
    sub[0xA20F] = _rational(pixels_per_cm, 1000)  # FocalPlaneYResolution
    sub[0xA210] = 3  # FocalPlaneResolutionUnit: centimetre
    if gps is not None:
        exif.get_ifd(GPS_IFD).update(_gps_tags(*gps))
    return exif.tobytes()


def _gps_tags(lat: float, lon: float, alt_m: float) -> dict[int, object]:
    """GPS IFD entries; Pillow knows their EXIF types (BYTE, ASCII, RATIONAL) from the tag numbers."""
    return {
        0: b"\x02\x03\x00\x00",  # GPSVersionID 2.3.0.0 (a tuple makes Pillow warn)
        1: "N" if lat >= 0 else "S",
        2: _dms(lat),
        3: "E" if lon >= 0 else "W",
        4: _dms(lon),
        5: 0 if alt_m >= 0 else 1,  # GPSAltitudeRef: above / below sea level
        6: _rational(abs(alt_m), 1000),
        18: "WGS-84",  # GPSMapDatum
    }


def _dms(degrees: float) -> tuple[TiffImagePlugin.IFDRational, ...]:
    """``|degrees|`` as degrees, minutes and micro-arcseconds: 3e-10 degree resolution."""
    micro_arcsec = round(abs(degrees) * 3600 * 1_000_000)
    deg, rest = divmod(micro_arcsec, 3600 * 1_000_000)
    minutes, micro = divmod(rest, 60 * 1_000_000)
    return (
        TiffImagePlugin.IFDRational(deg, 1),
        TiffImagePlugin.IFDRational(minutes, 1),
        TiffImagePlugin.IFDRational(micro, 1_000_000),
    )


def _rational(value: float, denominator: int) -> TiffImagePlugin.IFDRational:
    return TiffImagePlugin.IFDRational(round(value * denominator), denominator)


def write_bad_files(out_dir: Path) -> dict[str, Path]:
    """Write uploads a service must refuse, and return their paths by kind.

    Returns
    -------
    dict
        ``"not_image"``: a ``.jpg`` holding text. ``"truncated"``: a valid JPEG cut to 60 % of its
        bytes (``Image.open`` succeeds, ``load`` fails). ``"empty"``: 0 bytes. ``"bomb"``: a JPEG of a
        few hundred bytes whose header declares 50000x50000 px (Pillow's default
        ``MAX_IMAGE_PIXELS`` makes ``Image.open`` raise ``DecompressionBombError``).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    photo = _jpeg(make_texture(240, 320, seed=1))
    contents = {
        "not_image": b"This is a text file with a .jpg name, not a photo.\n" * 4,
        "truncated": photo[: int(0.6 * len(photo))],
        "empty": b"",
        "bomb": _bomb_jpeg(),
    }
    paths = {}
    for kind, data in contents.items():
        paths[kind] = out_dir / f"{kind}.jpg"
        paths[kind].write_bytes(data)
    return paths


def _jpeg(bgr: np.ndarray, quality: int = 90) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)).save(buf, "JPEG", quality=quality)
    return buf.getvalue()


def _bomb_jpeg() -> bytes:
    """A tiny real JPEG whose start-of-frame segment is patched to declare ``BOMB_SIDE`` px a side."""
    data = bytearray(_jpeg(make_texture(16, 16, seed=2)))
    sof = _sof0_offset(data)
    # SOF0 segment: marker (2), length (2), precision (1), height (2), width (2), ...
    struct.pack_into(">HH", data, sof + 5, BOMB_SIDE, BOMB_SIDE)
    return bytes(data)


def _sof0_offset(jpeg: bytes | bytearray) -> int:
    """Offset of the baseline start-of-frame marker, found by walking the segments after SOI."""
    pos = 2
    while pos + 4 <= len(jpeg) and jpeg[pos] == 0xFF:
        if jpeg[pos + 1] == 0xC0:
            return pos
        (length,) = struct.unpack_from(">H", jpeg, pos + 2)
        pos += 2 + length
    raise RuntimeError("Pillow wrote no baseline SOF0 segment before the image data")


def _translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1, 0, tx], [0, 1, ty], [0, 0, 1]], np.float64)


def _normalised(hom: np.ndarray) -> np.ndarray:
    return hom / hom[2, 2]


def _apply_homography(hom: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map ``(N, 2)`` points ``(x, y)`` through ``(3, 3)`` ``hom``; returns ``(N, 2) float64``."""
    mapped = np.column_stack([points, np.ones(len(points))]) @ hom.T
    return mapped[:, :2] / mapped[:, 2:3]
