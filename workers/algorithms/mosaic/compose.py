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
    feather_weights,
    gain_compensation,
    overlap_statistics,
    warp_maps,
    warp_maps_strided,
)
from workers.algorithms.mosaic.multiband import blend_bands, margin_px, ownership
from workers.algorithms.mosaic.vignetting import falloff, fit_vignetting, radius2

OVERVIEW_PX = 768  # longest side of the low-resolution render used for gains and the footprint


def output_box(to_frame: np.ndarray, size: tuple[int, int], width: int, height: int) -> tuple[int, int, int, int]:
    """Output pixel bbox (x0, y0, x1, y1) of a frame of ``size`` (width, height) px, clipped to the grid."""
    c = apply_homography(np.linalg.inv(to_frame), frame_corners(*size))
    x0, y0 = np.floor(c.min(axis=0)).astype(int) - 1
    x1, y1 = np.ceil(c.max(axis=0)).astype(int) + 1
    return max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)


def compose_block(
    image_of: Callable[[int], np.ndarray],
    sizes: dict[int, tuple[int, int]],
    to_frame: dict[int, np.ndarray],
    boxes: dict[int, tuple[int, int, int, int]],
    gains: dict[int, np.ndarray],
    window: tuple[int, int, int, int],
    feather_px: float,
    vignette: tuple[float, float] = (0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """One output window ``(x, y, w, h)``: every frame that reaches it warped, gain-corrected and feathered
    (and its lens fall-off ``vignette`` undone, :func:`~workers.algorithms.mosaic.vignetting.falloff`).

    ``image_of(k)`` gives frame ``k``'s (H, W, 3) uint8 BGR pixels, ``sizes[k]`` its (W, H); ``to_frame[k]`` maps
    output px to its px (memory-mapped: only the rows and columns
    the window needs are read). Returns (h, w, 3) uint8 RGB and (h, w) bool coverage.

    Each frame is warped only over the part of the window its box covers, by ``cv2.warpPerspective``
    (the same bilinear sampling as ``cv2.remap`` on :func:`warp_maps`, without building the maps), and its
    feathering weight comes from :func:`_feather_window`. The products, sums and the final division are
    OpenCV's SIMD array operations: NumPy's broadcasting of a (h, w) weight over 3 channels cost as much
    as the warps (measured on the Brighton strip: 1.4 s -> 0.9 s of CPU for its 16 windows).
    """
    x, y, w, h = window
    acc = np.zeros((h, w, 3), np.float32)
    wsum = np.zeros((h, w), np.float32)
    for k, (bx0, by0, bx1, by1) in boxes.items():
        sx0, sy0, sx1, sy1 = max(bx0, x), max(by0, y), min(bx1, x + w), min(by1, y + h)
        if sx1 <= sx0 or sy1 <= sy0:
            continue
        sub = (sx0, sy0, sx1 - sx0, sy1 - sy0)
        if vignette == (0.0, 0.0):
            weight, rho2 = _edge_weight(to_frame[k], sub, *sizes[k], feather_px), None
        else:
            weight, rho2 = _feather_window(to_frame[k], sub, *sizes[k], feather_px, with_radius=True)
        if not cv2.countNonZero(weight):
            continue
        pixels = _warp(image_of(k), to_frame[k], sub)
        g = gains[k].astype(np.float32)
        scaled = weight if rho2 is None else weight / falloff(rho2, vignette)  # brightness, not blending weight
        weighted = cv2.multiply(pixels, cv2.merge([scaled * g[0], scaled * g[1], scaled * g[2]]), dtype=cv2.CV_32F)
        rows, cols = slice(sy0 - y, sy1 - y), slice(sx0 - x, sx1 - x)
        acc_view, wsum_view = acc[rows, cols], wsum[rows, cols]
        cv2.add(acc_view, weighted, dst=acc_view)
        cv2.add(wsum_view, weight, dst=wsum_view)
    mask = wsum > 0
    inverse = cv2.divide(1.0, np.maximum(wsum, np.float32(1e-6)))
    # where no frame reaches, acc is 0 and so is the pixel; convertScaleAbs rounds and saturates to uint8
    bgr = cv2.convertScaleAbs(cv2.multiply(acc, cv2.merge([inverse, inverse, inverse])))
    return bgr[..., ::-1], mask


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
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`compose_block` with seams and multiband blending (:mod:`~workers.algorithms.mosaic.multiband`):
    each frame that owns part of the window, warped over the window and a margin, blended band by band by
    its ownership (``labels`` at ``label_scale``). Same returns."""
    x, y, w, h = window
    m = margin_px(bands)
    padded = (x - m, y - m, w + 2 * m, h + 2 * m)
    images, weights = [], []
    covered = np.zeros((h, w), bool)
    for k, (bx0, by0, bx1, by1) in boxes.items():
        if min(bx1, x + w + m) <= max(bx0, x - m) or min(by1, y + h + m) <= max(by0, y - m):
            continue
        edge, rho2 = _feather_window(to_frame[k], padded, *sizes[k], 1.0, with_radius=vignette != (0.0, 0.0))
        valid = edge > 0
        if not valid.any():
            continue
        covered |= valid[m : m + h, m : m + w]
        # a pixel the low-resolution cut left to no frame (at the render's edge) still gets its covering frames
        weight = ownership(labels, label_scale, k, padded) * valid + np.float32(1e-3) * valid
        if weight.max() <= 2e-3 and not valid[m : m + h, m : m + w].any():
            continue
        g = gains[k].astype(np.float32)
        warped = _warp(image_of(k), to_frame[k], padded).astype(np.float32)
        scale = np.ones(warped.shape[:2], np.float32) if rho2 is None else 1.0 / falloff(rho2, vignette)
        images.append(cv2.multiply(warped, cv2.merge([scale * v for v in g])))
        weights.append(weight.astype(np.float32))
    if not images:
        return np.zeros((h, w, 3), np.uint8), covered
    blended = blend_bands(images, weights, bands)[m : m + h, m : m + w]
    bgr = np.clip(blended + 0.5, 0, 255).astype(np.uint8)
    bgr[~covered] = 0
    return bgr[..., ::-1], covered


FEATHER_STEP_PX = 8  # _feather_window: the edge distance is evaluated every this many output px


def _feather_window(
    to_frame: np.ndarray,
    window: tuple[int, int, int, int],
    width: int,
    height: int,
    ramp_px: float,
    with_radius: bool = False,
) -> tuple[np.ndarray, np.ndarray | None]:
    """(h, w) float32 feathering weight of a ``width`` x ``height`` frame over an output ``window``:
    :func:`feather_weights` of :func:`warp_maps`, with the maps computed every ``FEATHER_STEP_PX`` output px
    and interpolated bilinearly in between.

    A homography's maps are smooth (exactly linear for an affine map), so the interpolation moves them by
    a small fraction of a px over a few px of perspective curvature; the weight is then found from them at
    full resolution, so the creases of the distance to the frame's edge stay sharp. Building the
    full-resolution maps in float64 cost a third of composing.
    """
    x, y, w, h = window
    step = FEATHER_STEP_PX
    coarse = cv2.merge(warp_maps_strided(to_frame, x, y, w // step + 2, h // step + 2, step))
    # fine pixel (i, j) sits at coarse position (i / step, j / step)
    zoom = np.array([[1.0 / step, 0.0, 0.0], [0.0, 1.0 / step, 0.0]])
    fine = cv2.warpAffine(coarse, zoom, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    weight = feather_weights(fine[..., 0], fine[..., 1], width, height, ramp_px)
    return weight, radius2(fine[..., 0], fine[..., 1], width, height) if with_radius else None


def _edge_weight(
    to_frame: np.ndarray, window: tuple[int, int, int, int], width: int, height: int, ramp_px: float
) -> np.ndarray:
    """:func:`_feather_window`'s weight, by warping the frame's distance to its nearest edge.

    That distance is the lower envelope of four planes in frame pixels, so the bilinear resampling of
    ``cv2.warpPerspective`` reproduces it exactly except within a pixel of the creases where two edges are
    equally near (the frame's diagonals near its corners), where it is slightly lower. It is built over the
    frame pixels the window maps onto (not clamped to the frame: negative outside, so the weight's edge falls
    where the distance is 0, as the map-based weight's does) from two 1-D profiles, and costs one warp where
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
    warped = cv2.warpPerspective(distance, shift_crop @ to_frame @ shift_out, (w, h), flags=flags,
                                 borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
    return np.clip(warped * np.float32(1.0 / ramp_px), 0.0, 1.0)


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
    """Bilinear samples of ``image`` (H, W, 3) at the maps, reading only the rows/columns needed."""
    xs, ys = map_x[valid], map_y[valid]
    c0, r0 = max(int(math.floor(xs.min())) - 1, 0), max(int(math.floor(ys.min())) - 1, 0)
    c1, r1 = min(int(math.ceil(xs.max())) + 2, image.shape[1]), min(int(math.ceil(ys.max())) + 2, image.shape[0])
    crop = np.ascontiguousarray(image[r0:r1, c0:c1])
    out = cv2.remap(crop, map_x - c0, map_y - r0, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.astype(np.float32)


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
        map_x, map_y = warp_maps(to_frame[k] @ low_to_out, 0, 0, lw, lh)
        inside = feather_weights(map_x, map_y, *sizes[k], 2.0 / r) >= 1.0
        image = image_of(k)
        images.append(_sample(image, map_x, map_y, inside) if inside.any() else np.zeros((lh, lw, 3), np.float32))
        masks.append(inside)
        radii.append(radius2(map_x, map_y, *sizes[k]))
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
