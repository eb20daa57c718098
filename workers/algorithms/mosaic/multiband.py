"""Seams and multiband blending (Burt & Adelson 1983; Brown & Lowe 2007, sec. 6; OpenCV's
``detail::GraphCutSeamFinder`` and ``detail::MultiBandBlender``).

Every mosaic pixel is owned by one frame: the owners come from a graph cut through the overlaps on a
low-resolution render (the cut runs where the frames' colours and gradients agree, so a car or a tree's
parallax ends up whole on one side). Each output window is then blended band by band: the frames' Laplacian
pyramids weighted by the Gaussian pyramids of their ownership, so fine detail switches sharply at the seam
and coarse brightness blends over a wide band. A window is composed with a margin wide enough for the
coarsest band, so window edges never show and memory stays that of a window.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from workers.algorithms.mosaic.blending import feather_weights, warp_maps

SEAM_PX = 512  # longest side of the render the seams are cut on (cv2.Stitcher cuts at about 0.1 MP)


def seam_labels(
    image_of: Callable[[int], np.ndarray],
    sizes: dict[int, tuple[int, int]],
    to_frame: dict[int, np.ndarray],
    gains: dict[int, np.ndarray],
    width: int,
    height: int,
) -> tuple[np.ndarray, float]:
    """(lh, lw) int32 owner of every pixel of a low-resolution render of the output grid (-1: no frame) and
    that render's scale (low-res px per output px).

    Frames are rendered gain-corrected, so the cut sees the colours the mosaic will show.
    """
    r = min(1.0, SEAM_PX / max(width, height))
    lw, lh = max(1, round(width * r)), max(1, round(height * r))
    low_to_out = np.diag([1 / r, 1 / r, 1.0])
    keys = sorted(to_frame)
    images, masks = [], []
    for k in keys:
        map_x, map_y = warp_maps(to_frame[k] @ low_to_out, 0, 0, lw, lh)
        inside = feather_weights(map_x, map_y, *sizes[k], 1.0) > 0
        pixels = np.zeros((lh, lw, 3), np.float32)
        if inside.any():
            pixels = _sample_low(image_of(k), map_x, map_y) * gains[k].astype(np.float32)[None, None, :]
        images.append(pixels)
        masks.append(inside.astype(np.uint8) * np.uint8(255))
    labels = np.full((lh, lw), -1, np.int32)
    # each frame cut to its own box with that box's corner: the finder builds a graph per overlap of boxes
    boxes = [_bbox(m) for m in masks]
    crops = [(images[n][y0:y1, x0:x1], masks[n][y0:y1, x0:x1]) for n, (x0, y0, x1, y1) in enumerate(boxes)]
    if len(keys) > 1:
        finder = cv2.detail_GraphCutSeamFinder("COST_COLOR_GRAD")  # type: ignore[attr-defined]
        found = finder.find(
            [np.ascontiguousarray(c[0]) for c in crops],
            [(b[0], b[1]) for b in boxes],
            [cv2.UMat(np.ascontiguousarray(c[1])) for c in crops],  # type: ignore[call-overload]
        )
        owned = [np.asarray(cv2.UMat.get(m) if isinstance(m, cv2.UMat) else m) for m in found]
    else:
        owned = [c[1] for c in crops]
    for n in range(len(keys) - 1, -1, -1):  # a pixel left to two frames goes to the first
        x0, y0, x1, y1 = boxes[n]
        view = labels[y0:y1, x0:x1]
        view[owned[n] > 0] = keys[n]
    return labels, r


def _bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) of a mask's non-zero pixels; a 1 px box at the origin for an empty one."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not len(rows):
        return 0, 0, 1, 1
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def _sample_low(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at the maps, reading only the rows and columns they reach."""
    c0 = max(int(np.floor(np.nanmin(map_x))) - 1, 0)
    r0 = max(int(np.floor(np.nanmin(map_y))) - 1, 0)
    c1 = min(int(np.ceil(np.nanmax(map_x))) + 2, image.shape[1])
    r1 = min(int(np.ceil(np.nanmax(map_y))) + 2, image.shape[0])
    if c1 <= c0 or r1 <= r0:
        return np.zeros((*map_x.shape, 3), np.float32)
    crop = np.ascontiguousarray(image[r0:r1, c0:c1])
    return cv2.remap(crop, map_x - c0, map_y - r0, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float32)


def margin_px(bands: int) -> int:
    """Margin a window needs so its coarsest band is what the whole mosaic's would be there: each pyrDown's
    5-tap kernel reaches 2 px of its level, 2^(l+1) output px at level l, summed over the levels."""
    return int(sum(2 ** (level + 1) for level in range(bands + 1))) + 2**bands


LabelWindow = tuple[np.ndarray, int, int]  # labels' cells, the column and row of its first cell


def label_window(labels: np.ndarray, scale: float, window: tuple[int, int, int, int]) -> LabelWindow:
    """The cells of the low-resolution ``labels`` (at ``scale``) that an output ``window``'s bilinear
    :func:`ownership` reads, with a cell to spare: (cells, first column, first row). At the labels' edge, the
    edge cells (which the warp replicates)."""
    x, y, w, h = window
    lh, lw = labels.shape
    lx0 = min(max(int(np.floor((x + 0.5) * scale - 0.5)) - 1, 0), lw - 1)
    ly0 = min(max(int(np.floor((y + 0.5) * scale - 0.5)) - 1, 0), lh - 1)
    lx1 = max(min(int(np.floor((x + w - 0.5) * scale - 0.5)) + 3, lw), lx0 + 1)
    ly1 = max(min(int(np.floor((y + h - 0.5) * scale - 0.5)) + 3, lh), ly0 + 1)
    return labels[ly0:ly1, lx0:lx1], lx0, ly0


def ownership(
    labels: np.ndarray, scale: float, k: int, window: tuple[int, int, int, int], near: LabelWindow | None = None
) -> np.ndarray:
    """(h, w) float32 in [0, 1]: where frame ``k`` owns output ``window``, the low-resolution labels brought
    to full resolution bilinearly (a seam a few output px wide, which the bands then shape). ``near``: the
    window's :func:`label_window`, when already cut."""
    x, y, w, h = window
    cells, lx0, ly0 = label_window(labels, scale, window) if near is None else near
    owned = (cells == k).astype(np.float32)
    # output pixel centre (x + i + 0.5) -> low-res pixel centre coordinate (x + i + 0.5) * scale - 0.5
    M = np.array([[scale, 0.0, (x + 0.5) * scale - 0.5 - lx0], [0.0, scale, (y + 0.5) * scale - 0.5 - ly0]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    return cv2.warpAffine(owned, M, (w, h), flags=flags, borderMode=cv2.BORDER_REPLICATE)


def blend_bands(images: list[np.ndarray], weights: list[np.ndarray], bands: int) -> np.ndarray:
    """Multiband blend of (h, w, 3) float32 ``images`` by (h, w) float32 ``weights``: band l of the result is
    the weights' Gaussian level l average of the images' Laplacian band l. Returns (h, w, 3) float32.

    OpenCV's array operations throughout: NumPy's broadcasting of a weight over 3 channels cost as much as
    the pyramids."""
    h, w = images[0].shape[:2]
    acc: list[np.ndarray] = []
    wsum: list[np.ndarray] = []
    for image, weight in zip(images, weights, strict=True):
        lap = _laplacian_pyramid(image, bands)
        gauss = _gaussian_pyramid(weight, bands)
        for level, (band, g) in enumerate(zip(lap, gauss, strict=True)):
            contribution = cv2.multiply(band, cv2.merge([g, g, g]))
            if level == len(acc):
                acc.append(contribution)
                wsum.append(g.copy())
            else:
                cv2.add(acc[level], contribution, dst=acc[level])
                cv2.add(wsum[level], g, dst=wsum[level])
    levels = []
    for a, s in zip(acc, wsum, strict=True):
        inverse = cv2.divide(1.0, np.maximum(s, np.float32(1e-6)))
        levels.append(cv2.multiply(a, cv2.merge([inverse, inverse, inverse])))
    out = levels[-1]
    for band in reversed(levels[:-1]):
        out = cv2.add(cv2.pyrUp(out, dstsize=(band.shape[1], band.shape[0])), band)
    return out[:h, :w]


def _gaussian_pyramid(image: np.ndarray, bands: int) -> list[np.ndarray]:
    levels = [image]
    for _ in range(bands):
        levels.append(cv2.pyrDown(levels[-1]))
    return levels


def _laplacian_pyramid(image: np.ndarray, bands: int) -> list[np.ndarray]:
    gauss = _gaussian_pyramid(image, bands)
    out = [
        cv2.subtract(fine, cv2.pyrUp(coarse, dstsize=(fine.shape[1], fine.shape[0])))
        for fine, coarse in zip(gauss[:-1], gauss[1:], strict=True)
    ]
    return [*out, gauss[-1]]


def owned_regions(labels: np.ndarray, scale: float) -> dict[int, list[np.ndarray]]:
    """Frame -> outline rings (N, 2) of the region it owns, output px, traced on the labels' render."""
    out: dict[int, list[np.ndarray]] = {}
    for k in np.unique(labels[labels >= 0]).tolist():
        contours, _ = cv2.findContours((labels == k).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        rings = [(c.reshape(-1, 2).astype(np.float64) + 0.5) / scale for c in contours if len(c) >= 3]
        if rings:
            out[int(k)] = rings
    return out


def seam_points(labels: np.ndarray, scale: float, limit: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """Points on the cut lines, output px (x, y), and the unit normal across the seam at each: where the owner
    changes between horizontal or vertical neighbours of the labels' render. At most ``limit``, evenly taken."""
    points, normals = [], []
    across_x = (labels[:, 1:] != labels[:, :-1]) & (labels[:, 1:] >= 0) & (labels[:, :-1] >= 0)
    rows, cols = np.nonzero(across_x)
    points.append(np.column_stack([(cols + 1) / scale, (rows + 0.5) / scale]))
    normals.append(np.tile([1.0, 0.0], (len(rows), 1)))
    across_y = (labels[1:, :] != labels[:-1, :]) & (labels[1:, :] >= 0) & (labels[:-1, :] >= 0)
    rows, cols = np.nonzero(across_y)
    points.append(np.column_stack([(cols + 0.5) / scale, (rows + 1) / scale]))
    normals.append(np.tile([0.0, 1.0], (len(rows), 1)))
    p, n = np.concatenate(points), np.concatenate(normals)
    keep = np.unique(np.linspace(0, len(p) - 1, min(limit, len(p))).astype(int)) if len(p) else np.zeros(0, int)
    return p[keep], n[keep]


def seam_visibility(
    read: Callable[[int, int, int, int], tuple[np.ndarray, np.ndarray]],
    points: np.ndarray,
    normals: np.ndarray,
    offset_px: int = 16,
) -> float | None:
    """How much the cut lines show in a mosaic: the mean colour step across them (between the pixels 1 px
    either side) over the same step measured ``offset_px`` to either side, parallel to the seam (1.0: the
    seam is as invisible as any line of the ground; feathering's and multiband's on the same seams compare).

    ``read(x, y, w, h)`` gives a window of the mosaic, (h, w, 3) and its (h, w) coverage; points whose profile
    leaves the coverage are skipped. None without any usable point.
    """
    steps, references = [], []
    reach = offset_px + 2
    for (x, y), (nx, _) in zip(points, normals, strict=True):
        cx, cy = int(np.floor(x)), int(np.floor(y))
        if nx:  # seam between columns cx - 1 and cx: a row of pixels across it
            pixels, mask = read(cx - reach, cy, 2 * reach, 1)
            line, ok = pixels[0].astype(np.float64), mask[0]
        else:
            pixels, mask = read(cx, cy - reach, 1, 2 * reach)
            line, ok = pixels[:, 0].astype(np.float64), mask[:, 0]
        if len(line) < 2 * reach or not ok.all():
            continue
        # the seam lies between line[reach - 1] and line[reach]; colour steps between neighbours, per px
        jumps = np.abs(np.diff(line, axis=0)).mean(axis=1)  # jumps[i]: between line[i] and line[i + 1]
        steps.append(float(jumps[reach - 1]))
        references.append(0.5 * float(jumps[reach - 1 - offset_px] + jumps[reach - 1 + offset_px]))
    if not steps or np.mean(references) <= 0:
        return None
    return float(np.mean(steps) / np.mean(references))
