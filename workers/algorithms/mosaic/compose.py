"""A mosaic's pixels, window by window: each frame's box on the output grid, gains and the coverage outline
from a low-resolution render, and one output window warped, gain-corrected and feather-blended (Brown &
Lowe 2007; OpenCV ``detail::FeatherBlender``). Memory depends on the window and frame size, never on the
size of the mosaic."""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np

from workers.algorithms.mosaic.alignment import apply_homography, frame_corners
from workers.algorithms.mosaic.blending import (
    edge_distance,
    feather_weights,
    gain_compensation,
    overlap_statistics,
    warp_maps,
    warp_maps_strided,
)
from workers.algorithms.mosaic.multiband import blend_bands, label_window, margin_px, ownership
from workers.algorithms.mosaic.vignetting import falloff, fit_vignetting, radius2

OVERVIEW_PX = 768  # longest side of the low-resolution render used for gains and the footprint


def output_box(to_frame: np.ndarray, size: tuple[int, int], width: int, height: int) -> tuple[int, int, int, int]:
    """Output pixel bbox (x0, y0, x1, y1) of a frame of ``size`` (width, height) px, clipped to the grid."""
    c = apply_homography(np.linalg.inv(to_frame), frame_corners(*size))
    x0, y0 = np.floor(c.min(axis=0)).astype(int) - 1
    x1, y1 = np.ceil(c.max(axis=0)).astype(int) + 1
    return max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)


Columns = dict[int, np.ndarray]  # frame -> (width,) float32 brightness of each of its columns (CCD gain undone)


def compose_block(
    image_of: Callable[[int], np.ndarray],
    sizes: dict[int, tuple[int, int]],
    to_frame: dict[int, np.ndarray],
    boxes: dict[int, tuple[int, int, int, int]],
    gains: dict[int, np.ndarray],
    window: tuple[int, int, int, int],
    feather_px: float,
    vignette: tuple[float, float] = (0.0, 0.0),
    columns: Columns | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One output window ``(x, y, w, h)``: every frame that reaches it warped, gain-corrected and feathered
    (and its lens fall-off ``vignette`` undone, :func:`~workers.algorithms.mosaic.vignetting.falloff`, and its
    columns brightened by ``columns[k]``, a strip camera's CCD sub-images evened out).

    ``image_of(k)`` gives frame ``k``'s (H, W, 3) uint8 BGR pixels, ``sizes[k]`` its (W, H); ``to_frame[k]`` maps
    output px to its px (memory-mapped: only the rows and columns
    the window needs are read). Returns (h, w, 3) uint8 RGB, (h, w) bool coverage and (h, w) int32 frame index:
    the frame of largest weight at each pixel (the one whose edge is farthest where several weigh 1; -1: none).

    Each frame is warped only over the part of the window its box covers, by ``cv2.warpPerspective``
    (the same bilinear sampling as ``cv2.remap`` on :func:`warp_maps`, without building the maps), and its
    feathering weight comes from :func:`_edge_distance`. The products, sums and the final division are
    OpenCV's SIMD array operations: NumPy's broadcasting of a (h, w) weight over 3 channels cost as much
    as the warps (measured on the Brighton strip: 1.4 s -> 0.9 s of CPU for its 16 windows).
    """
    x, y, w, h = window
    acc = np.zeros((h, w, 3), np.float32)
    wsum = np.zeros((h, w), np.float32)
    nearest = np.zeros((h, w), np.float32)  # the largest edge distance so far
    index = np.full((h, w), -1, np.int32)
    for k, (bx0, by0, bx1, by1) in boxes.items():
        sx0, sy0, sx1, sy1 = max(bx0, x), max(by0, y), min(bx1, x + w), min(by1, y + h)
        if sx1 <= sx0 or sy1 <= sy0:
            continue
        sub = (sx0, sy0, sx1 - sx0, sy1 - sy0)
        edge, rho2 = _edge_and_radius(to_frame[k], sub, *sizes[k], vignette != (0.0, 0.0))
        weight = np.clip(edge * np.float32(1.0 / feather_px), 0.0, 1.0)
        if not cv2.countNonZero(weight):
            continue
        pixels = _warp(image_of(k), to_frame[k], sub)
        g = gains[k].astype(np.float32)
        brightness = _brightness(to_frame[k], sub, rho2, vignette, None if columns is None else columns[k])
        scaled = weight if brightness is None else weight * brightness  # brightness, not blending weight
        weighted = cv2.multiply(pixels, cv2.merge([scaled * g[0], scaled * g[1], scaled * g[2]]), dtype=cv2.CV_32F)
        rows, cols = slice(sy0 - y, sy1 - y), slice(sx0 - x, sx1 - x)
        acc_view, wsum_view = acc[rows, cols], wsum[rows, cols]
        cv2.add(acc_view, weighted, dst=acc_view)
        cv2.add(wsum_view, weight, dst=wsum_view)
        deeper = edge > nearest[rows, cols]
        nearest[rows, cols][deeper] = edge[deeper]
        index[rows, cols][deeper] = k
    mask = wsum > 0
    index[~mask] = -1
    inverse = cv2.divide(1.0, np.maximum(wsum, np.float32(1e-6)))
    # where no frame reaches, acc is 0 and so is the pixel; convertScaleAbs rounds and saturates to uint8
    bgr = cv2.convertScaleAbs(cv2.multiply(acc, cv2.merge([inverse, inverse, inverse])))
    return bgr[..., ::-1], mask, index


def compose_block_multiband(
    image_of: Callable[[int], np.ndarray],
    sizes: dict[int, tuple[int, int]],
    to_frame: dict[int, np.ndarray],
    boxes: dict[int, tuple[int, int, int, int]],
    gains: dict[int, np.ndarray],
    window: tuple[int, int, int, int],
    labels: np.ndarray,
    label_scale: float,
    bands: int,
    vignette: tuple[float, float] = (0.0, 0.0),
    columns: Columns | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`compose_block` with seams and multiband blending (:mod:`~workers.algorithms.mosaic.multiband`):
    each frame that owns part of the window or its margin (``labels`` at ``label_scale``), warped over the part
    of both that its ownership reaches with the margin (:func:`_reach_box`), blended band by band by its
    ownership. Same returns; the frame index is the seam's owner.

    Only the owners are blended: a frame that reaches the window but owns nothing near it adds only where no
    owner covers a pixel (the low-resolution cut's edge). A window whose margin one frame owns alone is that
    frame's pixels, warped over the window only: the blend of a single image is the image (most windows of a
    mosaic lie away from its cut lines; on the Brighton strip this made multiband ~2x cheaper).
    """
    x, y, w, h = window
    m = margin_px(bands)
    padded = (x - m, y - m, w + 2 * m, h + 2 * m)
    centre = (slice(m, m + h), slice(m, m + w))
    near = label_window(labels, label_scale, padded)
    present = set(np.unique(near[0]).tolist())
    found: list[tuple[int, np.ndarray, np.ndarray | None]] = []  # frame, edge distance, ownership
    for k, (bx0, by0, bx1, by1) in boxes.items():
        if min(bx1, x + w + m) <= max(bx0, x - m) or min(by1, y + h + m) <= max(by0, y - m):
            continue
        # only where the frame is matters here (> 0), not how far inside: the warped distance, the cheapest
        edge = _edge_distance(to_frame[k], padded, *sizes[k])
        if not cv2.countNonZero((edge > 0).view(np.uint8)):
            continue
        found.append((k, edge, ownership(labels, label_scale, k, padded, near) if k in present else None))
    covered = np.zeros((h, w), bool)
    owned = np.zeros((h + 2 * m, w + 2 * m), np.float32)
    for _, edge, own in found:
        covered |= edge[centre] > 0
        if own is not None:
            owned += own * (edge > 0)
    orphans = (owned == 0) & np.any([edge > 0 for _, edge, _ in found], axis=0) if found else owned > 0
    blend = [f for f in found if (f[2] is not None and f[2].any()) or (orphans & (f[1] > 0)).any()]
    if not blend:
        return np.zeros((h, w, 3), np.uint8), covered, np.full((h, w), -1, np.int32)
    vignetted = vignette != (0.0, 0.0)
    if len(blend) == 1:
        k, edge, _ = blend[0]
        rho2 = _radius2(to_frame[k], window, *sizes[k]) if vignetted else None
        return _single_frame(image_of(k), to_frame[k], window, gains[k], edge[centre], rho2, vignette, columns, k)
    images, weights, corners = [], [], []
    index, best = np.full((h, w), -1, np.int32), np.zeros((h, w), np.float32)
    for k, edge, own in blend:
        valid = edge > 0
        reach = valid & ((own > 0) | orphans) if own is not None else valid & orphans
        bx0, by0, bx1, by1 = _reach_box(reach, m, 2**bands)
        part = (slice(by0, by1), slice(bx0, bx1))
        box = (x - m + bx0, y - m + by0, bx1 - bx0, by1 - by0)
        # a pixel the low-resolution cut left to no frame (at the render's edge) still gets its covering frames
        weight = valid[part].astype(np.float32) * (np.float32(1e-3) + (own[part] if own is not None else 0.0))
        warped = _warp(image_of(k), to_frame[k], box)
        rho2 = _radius2(to_frame[k], box, *sizes[k]) if vignetted else None
        images.append(_brightened(warped, gains[k], to_frame[k], box, rho2, vignette, columns, k))
        weights.append(weight)
        corners.append((bx0, by0))
        # the frame index: the frame of largest weight (the first of equal ones)
        cx0, cy0, cx1, cy1 = max(bx0, m), max(by0, m), min(bx1, m + w), min(by1, m + h)
        if cx1 > cx0 and cy1 > cy0:
            mine = weight[cy0 - by0 : cy1 - by0, cx0 - bx0 : cx1 - bx0]
            better = mine > best[cy0 - m : cy1 - m, cx0 - m : cx1 - m]
            index[cy0 - m : cy1 - m, cx0 - m : cx1 - m][better] = k
            best[cy0 - m : cy1 - m, cx0 - m : cx1 - m][better] = mine[better]
    blended = blend_bands(images, weights, bands, corners, (w + 2 * m, h + 2 * m))[centre]
    bgr = np.clip(blended + 0.5, 0, 255).astype(np.uint8)
    bgr[~covered] = 0
    index[~covered] = -1
    return bgr[..., ::-1], covered, index


def _reach_box(reach: np.ndarray, margin: int, align: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) of the part of a padded window a frame's blend is built over: where it has weight
    (``reach``) and ``margin`` px around, its corner on a multiple of ``align`` px, its far side too or at the
    window's edge (:func:`~workers.algorithms.mosaic.multiband.blend_bands`). Past the margin its pyramids'
    weight is that of the window's own margin (:func:`~workers.algorithms.mosaic.multiband.margin_px`): on the
    Brighton strip a blended frame's part was 57 % of the window on average."""
    rows, cols = np.flatnonzero(reach.any(axis=1)), np.flatnonzero(reach.any(axis=0))
    height, width = reach.shape
    x0, y0 = max(0, (cols[0] - margin) // align * align), max(0, (rows[0] - margin) // align * align)
    x1 = min(width, -(-(cols[-1] + 1 + margin) // align) * align)
    y1 = min(height, -(-(rows[-1] + 1 + margin) // align) * align)
    return int(x0), int(y0), int(x1), int(y1)


def _single_frame(
    image: np.ndarray,
    to_frame: np.ndarray,
    window: tuple[int, int, int, int],
    gain: np.ndarray,
    edge: np.ndarray,
    rho2: np.ndarray | None,
    vignette: tuple[float, float],
    columns: Columns | None,
    k: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A window one frame owns with its margin: its pixels, gain-corrected and brightened, where it is."""
    covered = edge > 0
    if not covered.any():  # it owns only some of the margin
        return np.zeros((*covered.shape, 3), np.uint8), covered, np.full(covered.shape, -1, np.int32)
    pixels = _brightened(_warp(image, to_frame, window), gain, to_frame, window, rho2, vignette, columns, k)
    bgr = np.clip(pixels + 0.5, 0, 255).astype(np.uint8)
    bgr[~covered] = 0
    return bgr[..., ::-1], covered, np.where(covered, np.int32(k), np.int32(-1))


def _brightened(
    warped: np.ndarray,
    gain: np.ndarray,
    to_frame: np.ndarray,
    window: tuple[int, int, int, int],
    rho2: np.ndarray | None,
    vignette: tuple[float, float],
    columns: Columns | None,
    k: int,
) -> np.ndarray:
    """(h, w, 3) float32: warped uint8 pixels times the frame's gain and :func:`_brightness`."""
    g = [float(v) for v in gain]
    brightness = _brightness(to_frame, window, rho2, vignette, None if columns is None else columns[k])
    if brightness is None:
        return cv2.multiply(warped, (g[0], g[1], g[2], 0.0), dtype=cv2.CV_32F)
    return cv2.multiply(warped, cv2.merge([brightness * v for v in g]), dtype=cv2.CV_32F)


def _brightness(
    to_frame: np.ndarray,
    window: tuple[int, int, int, int],
    rho2: np.ndarray | None,
    vignette: tuple[float, float],
    column_profile: np.ndarray | None,
) -> np.ndarray | None:
    """(h, w) float32 factor that undoes the lens fall-off (from ``rho2``) and a column's CCD gain over an output
    ``window``; None when there is neither."""
    factor = None if rho2 is None or vignette == (0.0, 0.0) else 1.0 / falloff(rho2, vignette)
    if column_profile is not None:
        along = _column_window(column_profile, to_frame, window)
        factor = along if factor is None else factor * along
    return factor


def _column_window(profile: np.ndarray, to_frame: np.ndarray, window: tuple[int, int, int, int]) -> np.ndarray:
    """(h, w) float32: a frame's per-column ``profile`` (W,) at each pixel of an output ``window`` (bilinear
    across columns, as the pixels are sampled): a one-row image warped with its border replicated down."""
    x, y, w, h = window
    corners = np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]], np.float64)
    src = apply_homography(to_frame, corners)
    c0 = max(int(np.floor(src[:, 0].min())) - 1, 0)
    c1 = min(int(np.ceil(src[:, 0].max())) + 2, len(profile))
    if c1 <= c0:
        return np.full((h, w), profile[0 if c0 == 0 else -1], np.float32)
    row = np.ascontiguousarray(profile[None, c0:c1], np.float32)
    shift_out = np.array([[1.0, 0.0, x + 0.5], [0.0, 1.0, y + 0.5], [0.0, 0.0, 1.0]])
    shift_crop = np.array([[1.0, 0.0, -c0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    return cv2.warpPerspective(row, shift_crop @ to_frame @ shift_out, (w, h), flags=flags,
                               borderMode=cv2.BORDER_REPLICATE)  # fmt: skip


FEATHER_STEP_PX = 8  # _edge_and_radius: the maps are evaluated every this many output px


def _edge_and_radius(
    to_frame: np.ndarray, window: tuple[int, int, int, int], width: int, height: int, with_radius: bool
) -> tuple[np.ndarray, np.ndarray | None]:
    """(h, w) float32 distance of each pixel of an output ``window`` to the nearest edge of a ``width`` x
    ``height`` frame (frame px; <= 0 outside it) and, ``with_radius``, its rho^2 in the frame
    (:func:`~workers.algorithms.mosaic.vignetting.radius2`).

    With the radius, the frame coordinates are computed every ``FEATHER_STEP_PX`` output px and interpolated
    bilinearly in between (a homography's maps are smooth: exactly linear for an affine map, so this moves them
    by a small fraction of a px; building the full-resolution maps in float64 cost a third of composing); the
    distance is then found from them at full resolution, so its creases stay sharp. Without it,
    :func:`_edge_distance`.
    """
    if not with_radius:
        return _edge_distance(to_frame, window, width, height), None
    fine = _coarse_maps(to_frame, window)
    edge = edge_distance(fine[..., 0], fine[..., 1], width, height)
    return edge, radius2(fine[..., 0], fine[..., 1], width, height)


def _radius2(to_frame: np.ndarray, window: tuple[int, int, int, int], width: int, height: int) -> np.ndarray:
    """(h, w) float32 rho^2 in the frame of each pixel of an output ``window``, as :func:`_edge_and_radius`'s."""
    fine = _coarse_maps(to_frame, window)
    return radius2(fine[..., 0], fine[..., 1], width, height)


def _coarse_maps(to_frame: np.ndarray, window: tuple[int, int, int, int]) -> np.ndarray:
    """(h, w, 2) float32 frame coordinates of an output ``window``'s pixels, computed every FEATHER_STEP_PX
    output px and interpolated bilinearly in between."""
    x, y, w, h = window
    step = FEATHER_STEP_PX
    coarse = cv2.merge(warp_maps_strided(to_frame, x, y, w // step + 2, h // step + 2, step))
    # fine pixel (i, j) sits at coarse position (i / step, j / step)
    zoom = np.array([[1.0 / step, 0.0, 0.0], [0.0, 1.0 / step, 0.0]])
    return cv2.warpAffine(coarse, zoom, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)


def _edge_distance(to_frame: np.ndarray, window: tuple[int, int, int, int], width: int, height: int) -> np.ndarray:
    """(h, w) float32 distance to the frame's nearest edge over an output ``window``, by warping that distance.

    It is the lower envelope of four planes in frame pixels, so the bilinear resampling of
    ``cv2.warpPerspective`` reproduces it exactly except within a pixel of the creases where two edges are
    equally near (the frame's diagonals near its corners), where it is slightly lower. It is built over the
    frame pixels the window maps onto (not clamped to the frame: negative outside, so the weight's edge falls
    where the distance is 0, as the map-based one's does) from two 1-D profiles, and costs one warp where
    building and interpolating the coordinate maps cost three times that.
    """
    x, y, w, h = window
    corners = np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]], np.float64)
    src = apply_homography(to_frame, corners)
    c0, r0 = (int(v) - 2 for v in np.floor(src.min(axis=0)))
    c1, r1 = (int(v) + 3 for v in np.ceil(src.max(axis=0)))
    xs, ys = np.arange(c0, c1, dtype=np.float32), np.arange(r0, r1, dtype=np.float32)
    along_x = np.minimum(xs + 0.5, width - 0.5 - xs)
    along_y = np.minimum(ys + 0.5, height - 0.5 - ys)
    distance = np.minimum.outer(along_y, along_x)
    shift_out = np.array([[1.0, 0.0, x + 0.5], [0.0, 1.0, y + 0.5], [0.0, 0.0, 1.0]])
    shift_crop = np.array([[1.0, 0.0, -c0], [0.0, 1.0, -r0], [0.0, 0.0, 1.0]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    return cv2.warpPerspective(distance, shift_crop @ to_frame @ shift_out, (w, h), flags=flags,
                               borderMode=cv2.BORDER_REPLICATE)  # fmt: skip


def _warp(image: np.ndarray, to_frame: np.ndarray, window: tuple[int, int, int, int]) -> np.ndarray:
    """(h, w, 3) uint8 bilinear samples of ``image`` over an output ``window``, reading only the frame
    rows and columns the window maps onto."""
    x, y, w, h = window
    corners = np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]], np.float64)
    src = apply_homography(to_frame, corners)
    c0, r0 = (max(int(v), 0) for v in np.floor(src.min(axis=0)) - 1)
    c1 = min(int(math.ceil(src[:, 0].max())) + 2, image.shape[1])
    r1 = min(int(math.ceil(src[:, 1].max())) + 2, image.shape[0])
    crop = np.ascontiguousarray(image[r0:r1, c0:c1])
    # window pixel (i, j) -> output pixel centre (x + i + 0.5, y + j + 0.5) -> frame px -> crop px
    shift_out = np.array([[1.0, 0.0, x + 0.5], [0.0, 1.0, y + 0.5], [0.0, 0.0, 1.0]])
    shift_crop = np.array([[1.0, 0.0, -c0], [0.0, 1.0, -r0], [0.0, 0.0, 1.0]])
    M = shift_crop @ to_frame @ shift_out
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    return cv2.warpPerspective(crop, M, (w, h), flags=flags, borderMode=cv2.BORDER_REPLICATE)


def _sample(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Bilinear samples (uint8) of ``image`` (H, W, 3) at the maps, reading only the rows/columns needed."""
    xs, ys = map_x[valid], map_y[valid]
    c0, r0 = max(int(math.floor(xs.min())) - 1, 0), max(int(math.floor(ys.min())) - 1, 0)
    c1, r1 = min(int(math.ceil(xs.max())) + 2, image.shape[1]), min(int(math.ceil(ys.max())) + 2, image.shape[0])
    crop = np.ascontiguousarray(image[r0:r1, c0:c1])
    return cv2.remap(crop, map_x - c0, map_y - r0, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def gains_and_coverage(
    image_of: Callable[[int], np.ndarray],
    sizes: dict[int, tuple[int, int]],
    to_frame: dict[int, np.ndarray],
    width: int,
    height: int,
    enabled: bool,
    vignetting: bool = False,
) -> tuple[dict[int, np.ndarray], list[np.ndarray], float, tuple[float, float]]:
    """Gains from a low-resolution render of every frame on the ``width`` x ``height`` output grid, and the
    mosaic's coverage: outline rings (N, 2) in output px and the share of the grid covered; with
    ``vignetting``, first the lens' radial fall-off (:mod:`~workers.algorithms.mosaic.vignetting`), which the
    gains are then measured without. Returns gains, outline, coverage and the fall-off's (c1, c2)."""
    r = min(1.0, OVERVIEW_PX / max(width, height))
    lw, lh = max(1, round(width * r)), max(1, round(height * r))
    low_to_out = np.diag([1 / r, 1 / r, 1.0])
    keys = sorted(to_frame)
    images, masks, radii = [], [], []
    for k in keys:
        low_to_frame = to_frame[k] @ low_to_out
        map_x, map_y = warp_maps(low_to_frame, 0, 0, lw, lh)
        # 2 low-resolution px in from the frame's edge, in frame px: an output px can be much finer than a
        # frame px (a strip's native mosaic over its 1/8 working copy), so not 2 / r frame px
        frame_px = float(np.sqrt(abs(np.linalg.det(low_to_frame[:2, :2] / low_to_frame[2, 2]))))
        inside = feather_weights(map_x, map_y, *sizes[k], 2.0 * frame_px) >= 1.0
        image = image_of(k)
        # uint8, as sampled (a quarter of float32's memory: every frame's render covers the whole grid)
        images.append(_sample(image, map_x, map_y, inside) if inside.any() else np.zeros((lh, lw, 3), np.uint8))
        masks.append(inside)
        # only where the frame is: far outside it rho^2 grows until the fall-off overflows (0 / inf warnings)
        radii.append(np.where(inside, radius2(map_x, map_y, *sizes[k]), np.float32(0.0)))
    vignette = fit_vignetting(images, masks, radii) if vignetting else (0.0, 0.0)
    if vignette != (0.0, 0.0):
        images = [im / falloff(rho2, vignette)[..., None] for im, rho2 in zip(images, radii, strict=True)]
    gains = np.ones((len(keys), 3))
    if enabled:
        means, counts = overlap_statistics(images, masks)
        gains = gain_compensation(means, counts)
    union = np.any(masks, axis=0).astype(np.uint8) if masks else np.zeros((lh, lw), np.uint8)
    contours, _ = cv2.findContours(union, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    outline = [(c.reshape(-1, 2).astype(np.float64) + 0.5) / r for c in contours if len(c) >= 3]
    return {k: gains[n] for n, k in enumerate(keys)}, outline, float(union.mean()), vignette
