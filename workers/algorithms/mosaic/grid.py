"""The output grid of a mosaic: a north-up grid in map units over the mosaic plane, or the plane itself."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from workers.algorithms.geometry import FLIP_Y, fit_similarity, lonlat_to_utm, similarity_scale, utm_epsg
from workers.algorithms.mosaic.alignment import apply_homography, frame_corners

MAX_OUTPUT_PIXELS = 4_000_000_000  # ortho mode: a larger grid means a ground range gone wrong
MAX_SPREAD = 1000.0  # planar: a grid this many times the frames' own area means the alignment broke
# disk a mosaic needs per output px while it is written: the COGs with their overviews (measured: about 1.2 B/px
# on drone mosaics, 1.7 on a synthetic strip's busy ground, deflate with predictor; 2 allows for busier ground)
# and a band: the bands are the COGs' own tiles, assembled into them and deleted as they are copied
# (workers/cog_writer.py): 1.01x the COGs on bench/cog_disk.py's 0.6 Gpx mosaic, where a scratch mosaic copied
# into a COG peaked at 2.74x. JPEG (quality 90) COGs took 0.36 B/px with their overviews and the frame index on
# the synthetic strip's ground (bench/strips.py, 20000 px frames); 0.75 allows for busier ground, as 2 does for
# the lossless codecs.
COG_BYTES_PER_PX = {"deflate": 2.0, "zstd": 2.0, "lzw": 2.0, "jpeg": 0.75}


def disk_needed(width: int, height: int, compression: str = "deflate") -> int:
    """Bytes of free disk a ``width`` x ``height`` mosaic needs while it is written (an estimate), its COG
    compressed with ``compression`` (a ``cog_compression`` option)."""
    # the COGs and their overviews' last tile rows, and a band being copied (512 rows at compose's default)
    return int(COG_BYTES_PER_PX[compression] * (width * height * 1.1 + width * 512))


def output_size_problem(
    width: int, height: int, frames_px: float | None, free_bytes: int, compression: str = "deflate"
) -> str | None:
    """Why a ``width`` x ``height`` px mosaic cannot be written, in words, or None.

    ``frames_px``: the frames' own area on the grid, summed (None: not checked). There is no fixed cap on the
    size: a gigapixel strip is fine where the disk holds it.
    """
    if frames_px is not None and width * height > MAX_SPREAD * max(frames_px, 1e6):
        return (
            f"the mosaic would be {width}x{height} px, {width * height / max(frames_px, 1):.0f} times its "
            "frames' area; the alignment is degenerate (frames do not lie in one plane)"
        )
    need = disk_needed(width, height, compression)
    if need > free_bytes:
        return (
            f"a {width}x{height} px mosaic needs about {need / 1e9:.1f} GB of free disk to be written and "
            f"{free_bytes / 1e9:.1f} GB are free; free some space or compose it coarser (working_max_px, "
            "output_resolution)"
        )
    return None


def photo_px_per_plane_px(H: np.ndarray, width: int, height: int, photo_width: int, photo_height: int) -> float:
    """How many of a photo's own px one plane px spans where the photo lies: ``H`` maps its working copy
    (``width`` x ``height``) to the plane, and the photo is ``photo_width`` x ``photo_height``. The plane is the
    reference working copy's only until the adjustment moves it (a strip's GPS levels and scales it: 0.90-0.95
    of the reference's size along a 305-frame strip), so this is measured, not assumed."""
    area = polygon_area(apply_homography(H, frame_corners(width, height)))
    return math.sqrt(photo_width * photo_height / area)


def polygon_area(corners: np.ndarray) -> float:
    """Area of a simple polygon (N, 2), shoelace formula, in the squared units of its coordinates."""
    x, y = corners[:, 0], corners[:, 1]
    return float(abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) / 2)


MIN_GPS_SPREAD_M = 3.0  # below this, consumer GPS noise would dominate the fitted scale and rotation


def fit_plane_to_map(centres: np.ndarray, latlon: np.ndarray) -> tuple[int, np.ndarray, np.ndarray] | str:
    """The similarity from the mosaic plane (px, y down) to UTM metres that best puts frame centres on their
    GPS fixes.

    ``centres`` (N, 2) plane px, ``latlon`` (N, 2) degrees. Returns ``(epsg, plane_to_map (3, 3), utm (N, 2))``,
    or why it cannot be fitted (a sentence).
    """
    epsg = utm_epsg(float(latlon[:, 0].mean()), float(latlon[:, 1].mean()))
    utm = lonlat_to_utm(latlon[:, ::-1], epsg)
    spread = float(np.linalg.norm(utm - utm.mean(axis=0), axis=1).max())
    if spread < MIN_GPS_SPREAD_M:
        return f"the GPS positions lie within {spread:.1f} m of each other; too close to fit a scale"
    S = fit_similarity(apply_homography(FLIP_Y, centres), utm)
    return epsg, S @ FLIP_Y, utm


def map_grid(plane_corners: np.ndarray, plane_to_map: np.ndarray) -> dict[str, Any]:
    """A north-up grid in map units covering every frame, at the plane's own resolution.

    ``plane_corners`` (N, 2) plane px; ``plane_to_map`` (3, 3). Returns ``width``, ``height`` (px), ``transform``
    (GDAL affine, 6 floats) and ``output_to_plane`` (3, 3).
    """
    M = np.array(plane_to_map)
    gsd = similarity_scale(M)
    xy = apply_homography(M, plane_corners)
    west, north = xy[:, 0].min(), xy[:, 1].max()
    width = math.ceil((xy[:, 0].max() - west) / gsd)
    height = math.ceil((north - xy[:, 1].min()) / gsd)
    affine = np.array([[gsd, 0.0, west], [0.0, -gsd, north], [0.0, 0.0, 1.0]])
    return {
        "width": width,
        "height": height,
        "transform": affine[:2].ravel().tolist(),
        "output_to_plane": np.linalg.inv(M) @ affine,
    }


def pixel_grid(plane_corners: np.ndarray) -> dict[str, Any]:
    """The plane itself, shifted so the mosaic starts at pixel (0, 0); no map coordinates."""
    x0, y0 = np.floor(plane_corners.min(axis=0))
    x1, y1 = np.ceil(plane_corners.max(axis=0))
    shift = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
    return {
        "width": int(x1 - x0),
        "height": int(y1 - y0),
        "transform": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
        "output_to_plane": shift,
    }


def refine_grid(grid: dict[str, Any], factor: float) -> dict[str, Any]:
    """A :func:`map_grid` or :func:`pixel_grid` with ``factor`` times as many px along each axis over the same
    ground (``factor`` 1.95: a mosaic at the photos' own resolution instead of the working copies').

    The grid keeps its origin (top left corner); the pixel size shrinks by ``factor``.
    """
    if factor <= 0:
        raise ValueError("factor must be positive")
    a, b, c, d, e, f = grid["transform"]
    zoom = np.diag([1.0 / factor, 1.0 / factor, 1.0])
    return {
        "width": math.ceil(grid["width"] * factor - 1e-9),
        "height": math.ceil(grid["height"] * factor - 1e-9),
        "transform": [a / factor, b / factor, c, d / factor, e / factor, f],
        "output_to_plane": np.asarray(grid["output_to_plane"]) @ zoom,
    }
