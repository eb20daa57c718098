"""SIFT keypoints and descriptors (Lowe 2004), array-module generic, following OpenCV's conventions
(angles in degrees counter-clockwise with image y pointing up, descriptors before uint8 scaling).

Stages, each vectorised over all candidates of an octave: DoG extrema in 3x3x3 neighbourhoods;
sub-pixel/sub-scale refinement by Newton steps on the DoG; contrast and edge (Hessian ratio) rejection;
orientation histograms (36 bins, smoothed, peaks above 0.8 of the maximum, up to
``max_orientations`` per point); descriptors of ``layout = (d, n)``: d x d cells of n orientation
bins, trilinear weighting, normalised, clipped at 0.2, normalised again.

Memory plan: the scale space of one octave (see ``scale_space``) plus, per chunk of ``chunk``
keypoints, the samples of their descriptor windows: (2R+1)^2 samples of about 40 bytes each, with
R ~ 10.6 sigma in octave pixels (about 8 MB a keypoint at the coarsest level, 2 GB per chunk of 256
at worst; lower ``chunk`` on a small GPU).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from gpu_kernels.backend import get_array_module, ndimage_module, to_host
from gpu_kernels.scale_space import Octave, scale_space

BORDER = 5  # px of an octave where no extremum is looked for (OpenCV's SIFT_IMG_BORDER)
MAX_STEPS = 5  # Newton steps of the refinement
ORI_BINS = 36
ORI_PEAK = 0.8


@dataclass(frozen=True)
class Keypoints:
    """SIFT keypoints, strongest first.

    ``xy`` (N, 2) float64 input pixels (float64: integer pixel + float32 sub-pixel offset + tile origin
    add up exactly, so tiled and untiled runs agree to the bit); ``sigma`` (N,) blur scale in input
    pixels; ``angle`` (N,) degrees; ``octave`` (N,) int; ``sign`` (N,) +1 for a DoG maximum, -1 for a
    minimum; ``response`` (N,) |DoG| at the extremum; ``descriptors`` (N, d*d*n) float32, unit length.
    """

    xy: Any
    sigma: Any
    angle: Any
    octave: Any
    sign: Any
    response: Any
    descriptors: Any


def sift(
    image: Any,
    first_octave: int = -1,
    octaves: int | None = None,
    levels: int = 3,
    sigma0: float = 1.6,
    contrast_threshold: float = 0.04,
    edge_threshold: float = 10.0,
    max_orientations: int = 4,
    layout: tuple[int, int] = (4, 8),
    max_features: int | None = None,
    chunk: int = 256,
) -> Keypoints:
    """Detect and describe SIFT keypoints of an (H, W) grey image (uint8 or float in [0, 1])."""
    xp = get_array_module(image)
    parts = []
    offset = -0.25 if first_octave == -1 else 0.0  # octave -1 samples input pixel centres at (i + 0.5)/2 - 0.5
    for octave in scale_space(image, first_octave, octaves, levels, sigma0):
        found = _octave_keypoints(octave, levels, sigma0, contrast_threshold, edge_threshold)
        if found is None:
            continue
        x, y, s_float, s_int, contrast = found
        sigma = _octave_sigma(s_float, levels, sigma0)
        angles, owner = _orientations(octave, x, y, s_int, sigma, max_orientations, 4 * chunk)
        x, y, s_float, s_int, contrast = x[owner], y[owner], s_float[owner], s_int[owner], contrast[owner]
        desc = _descriptors(octave, x, y, s_int, sigma[owner], angles, layout, chunk)
        parts.append(
            Keypoints(
                xy=xp.stack([x, y], axis=1).astype(xp.float64) * octave.spacing + offset,
                sigma=(_octave_sigma(s_float, levels, sigma0) * octave.spacing).astype(xp.float32),
                angle=angles,
                octave=xp.full(len(x), octave.index, xp.int32),
                sign=xp.sign(contrast).astype(xp.int8),
                response=xp.abs(contrast),
                descriptors=desc,
            )
        )
    return _concat(parts, xp, layout, max_features)


def _octave_sigma(s: Any, levels: int, sigma0: float) -> Any:
    return sigma0 * 2.0 ** (s / levels)


def _octave_keypoints(
    octave: Octave, levels: int, sigma0: float, contrast_threshold: float, edge_threshold: float
) -> tuple[Any, ...] | None:
    """Refined extrema of one octave: (x, y, s) sub-pixel, s rounded, contrast; None when there are none."""
    xp = get_array_module(octave.dog)
    dog = octave.dog
    nd = ndimage_module(xp)
    threshold = 0.5 * contrast_threshold / levels
    peak = (dog == nd.maximum_filter(dog, size=3, mode="nearest")) & (dog > threshold)
    pit = (dog == nd.minimum_filter(dog, size=3, mode="nearest")) & (dog < -threshold)
    candidates = peak | pit
    candidates[0] = candidates[-1] = False
    candidates[:, :BORDER] = candidates[:, -BORDER:] = False
    candidates[:, :, :BORDER] = candidates[:, :, -BORDER:] = False
    s, y, x = xp.nonzero(candidates)
    if len(s) == 0:
        return None
    return _refine(dog, s, y, x, levels, contrast_threshold, edge_threshold)


def _refine(
    dog: Any, s: Any, y: Any, x: Any, levels: int, contrast_threshold: float, edge_threshold: float
) -> tuple[Any, ...] | None:
    xp = get_array_module(dog)
    n_s, h, w = dog.shape
    alive = xp.ones(len(s), bool)
    converged = xp.zeros(len(s), bool)
    offset = xp.zeros((len(s), 3), dog.dtype)
    for _ in range(MAX_STEPS):
        grad, hess = _derivatives(dog, s, y, x)
        step = -xp.linalg.solve(hess + xp.eye(3, dtype=hess.dtype) * 1e-12, grad[..., None])[..., 0]
        step = xp.where(xp.isfinite(step), step, 1e6)
        done = xp.all(xp.abs(step) < 0.5, axis=1) & alive & ~converged
        offset[done] = step[done]
        converged |= done
        moving = alive & ~converged
        if not bool(moving.any()):
            break
        big = xp.any(xp.abs(step) > 1e3, axis=1)
        alive &= ~(moving & big)
        move = xp.where(moving[:, None] & ~big[:, None], xp.rint(step), 0).astype(xp.int64)
        x, y, s = x + move[:, 0], y + move[:, 1], s + move[:, 2]
        inside = (s >= 1) & (s <= n_s - 2) & (y >= BORDER) & (y < h - BORDER) & (x >= BORDER) & (x < w - BORDER)
        alive &= inside
        x, y, s = xp.clip(x, 1, w - 2), xp.clip(y, 1, h - 2), xp.clip(s, 1, n_s - 2)
    keep = alive & converged
    grad, hess = _derivatives(dog, s, y, x)
    contrast = dog[s, y, x] + 0.5 * (grad * offset).sum(axis=1)
    trace, det = hess[:, 0, 0] + hess[:, 1, 1], hess[:, 0, 0] * hess[:, 1, 1] - hess[:, 0, 1] ** 2
    r = edge_threshold
    keep &= (xp.abs(contrast) * levels >= contrast_threshold) & (det > 0) & (trace * trace * r < (r + 1) ** 2 * det)
    if not bool(keep.any()):
        return None
    k = xp.nonzero(keep)[0]
    return (x[k] + offset[k, 0], y[k] + offset[k, 1], s[k] + offset[k, 2], s[k], contrast[k])


def _derivatives(dog: Any, s: Any, y: Any, x: Any) -> tuple[Any, Any]:
    """Gradient (N, 3) and Hessian (N, 3, 3) of the DoG by central differences, order (x, y, s)."""
    xp = get_array_module(dog)

    def d(ds: int, dy: int, dx: int) -> Any:
        return dog[s + ds, y + dy, x + dx]

    v = d(0, 0, 0)
    grad = 0.5 * xp.stack([d(0, 0, 1) - d(0, 0, -1), d(0, 1, 0) - d(0, -1, 0), d(1, 0, 0) - d(-1, 0, 0)], axis=1)
    dxx, dyy, dss = d(0, 0, 1) + d(0, 0, -1) - 2 * v, d(0, 1, 0) + d(0, -1, 0) - 2 * v, d(1, 0, 0) + d(-1, 0, 0) - 2 * v
    dxy = 0.25 * (d(0, 1, 1) - d(0, 1, -1) - d(0, -1, 1) + d(0, -1, -1))
    dxs = 0.25 * (d(1, 0, 1) - d(1, 0, -1) - d(-1, 0, 1) + d(-1, 0, -1))
    dys = 0.25 * (d(1, 1, 0) - d(1, -1, 0) - d(-1, 1, 0) + d(-1, -1, 0))
    hess = xp.stack([xp.stack([dxx, dxy, dxs], 1), xp.stack([dxy, dyy, dys], 1), xp.stack([dxs, dys, dss], 1)], 1)
    return grad, hess


def _level_windows(image: Any, cx: Any, cy: Any, radius: Any) -> tuple[Any, Any, Any, Any, Any]:
    """:func:`_window_gradients` for keypoints of different (N,) window radii at once: every window as large as
    the largest, each masked to its own (2R+1)^2 square. The masked samples weigh exactly 0, so the histograms
    are those of a pass per radius, which took a few launches and two host reads for each of the 20-60 radii of
    an octave: on a GPU, SIFT on 800 x 600 px took 0.71 s against OpenCV's 0.05 (bench/kernels.py, H200)."""
    xp = get_array_module(image)
    i, j, dx, dy, valid = _window_gradients(image, cx, cy, int(radius.max()) if len(radius) else 0)
    own = radius[:, None]
    return i, j, dx, dy, valid & (xp.abs(i) <= own) & (xp.abs(j) <= own)


def _window_gradients(image: Any, cx: Any, cy: Any, radius: int) -> tuple[Any, Any, Any, Any, Any]:
    """Gradients on the (2R+1)^2 window around integer centres: offsets i (rows), j (cols), dx, dy
    (y up, as OpenCV), and the mask of samples with both neighbours inside the image. (N, P) each."""
    xp = get_array_module(image)
    h, w = image.shape
    offs = xp.arange(-radius, radius + 1)
    i = xp.repeat(offs, len(offs))[None, :]
    j = xp.tile(offs, len(offs))[None, :]
    r, c = cy[:, None] + i, cx[:, None] + j
    valid = (r > 0) & (r < h - 1) & (c > 0) & (c < w - 1)
    rc, cc = xp.clip(r, 1, h - 2), xp.clip(c, 1, w - 2)
    dx = image[rc, cc + 1] - image[rc, cc - 1]
    dy = image[rc - 1, cc] - image[rc + 1, cc]
    return i, j, dx, dy, valid


def _orientations(
    octave: Octave, x: Any, y: Any, s_int: Any, sigma: Any, max_orientations: int, chunk: int
) -> tuple[Any, Any]:
    """Dominant gradient orientations: (M,) angles in degrees and (M,) index of the keypoint of each; ``chunk``
    keypoints at a time (their windows' side is 9 sigma, the descriptors' 21: 4 x their chunk is less memory)."""
    xp = get_array_module(x)
    cx, cy = xp.rint(x).astype(xp.int64), xp.rint(y).astype(xp.int64)
    radius = xp.rint(3 * 1.5 * sigma).astype(xp.int64)
    hist = xp.zeros((len(x), ORI_BINS), xp.float32)
    for lvl in np.unique(to_host(s_int)).tolist():  # one vectorised pass per level and chunk (_level_windows)
        members = xp.nonzero(s_int == lvl)[0]
        for start in range(0, len(members), chunk):
            kk = members[start : start + chunk]
            i, j, dx, dy, valid = _level_windows(octave.gaussians[lvl], cx[kk], cy[kk], radius[kk])
            weight = xp.exp(-(i * i + j * j) / (2.0 * (1.5 * sigma[kk, None]) ** 2)) * valid
            bins = xp.rint(xp.degrees(xp.arctan2(dy, dx)) * ORI_BINS / 360.0).astype(xp.int64) % ORI_BINS
            flat = (xp.arange(len(kk))[:, None] * ORI_BINS + bins).ravel()
            mag = xp.sqrt(dx * dx + dy * dy) * weight
            hist[kk] = xp.bincount(flat, weights=mag.ravel(), minlength=len(kk) * ORI_BINS).reshape(-1, ORI_BINS)
    smooth = sum(wt * xp.roll(hist, sh, axis=1) for sh, wt in ((-2, 1), (-1, 4), (0, 6), (1, 4), (2, 1))) / 16.0
    left, right = xp.roll(smooth, 1, axis=1), xp.roll(smooth, -1, axis=1)
    is_peak = (smooth > left) & (smooth > right) & (smooth >= ORI_PEAK * smooth.max(axis=1, keepdims=True))
    ranked = xp.argsort(-xp.where(is_peak, smooth, -1.0), axis=1)[:, :max_orientations]
    chosen = xp.take_along_axis(is_peak, ranked, axis=1)
    owner, slot = xp.nonzero(chosen)
    b = ranked[owner, slot]
    lv, cv, rv = left[owner, b], smooth[owner, b], right[owner, b]
    refined = b + 0.5 * (lv - rv) / (lv - 2 * cv + rv)
    angle = (360.0 - refined * (360.0 / ORI_BINS)) % 360.0
    return angle.astype(xp.float32), owner


def _descriptors(
    octave: Octave, x: Any, y: Any, s_int: Any, sigma: Any, angle: Any, layout: tuple[int, int], chunk: int
) -> Any:
    xp = get_array_module(x)
    d, n = layout
    out = xp.zeros((len(x), d * d * n), xp.float32)
    cx, cy = xp.rint(x).astype(xp.int64), xp.rint(y).astype(xp.int64)
    hist_width = 3.0 * sigma
    radius = xp.rint(hist_width * math.sqrt(2.0) * (d + 1) * 0.5).astype(xp.int64)
    for lvl in np.unique(to_host(s_int)).tolist():  # one vectorised pass per level and chunk (_level_windows)
        members = xp.nonzero(s_int == lvl)[0]
        for start in range(0, len(members), chunk):
            k = members[start : start + chunk]
            out[k] = _describe(octave.gaussians[lvl], cx[k], cy[k], hist_width[k], angle[k], radius[k], d, n)
    return out


def _describe(image: Any, cx: Any, cy: Any, hist_width: Any, angle: Any, radius: Any, d: int, n: int) -> Any:
    """OpenCV's calcSIFTDescriptor for a batch of keypoints of one level, each in its own (N,) window radius."""
    xp = get_array_module(image)
    i, j, dx, dy, valid = _level_windows(image, cx, cy, radius)
    ori = ((360.0 - angle) % 360.0)[:, None]  # OpenCV describes in the unflipped histogram angle
    theta = xp.radians(ori)
    cos_t, sin_t = xp.cos(theta) / hist_width[:, None], xp.sin(theta) / hist_width[:, None]
    c_rot, r_rot = j * cos_t - i * sin_t, j * sin_t + i * cos_t
    rbin, cbin = r_rot + d / 2 - 0.5, c_rot + d / 2 - 0.5
    valid &= (rbin > -1) & (rbin < d) & (cbin > -1) & (cbin < d)
    weight = xp.exp(-(c_rot**2 + r_rot**2) / (d * d * 0.5))
    mag = xp.sqrt(dx * dx + dy * dy) * weight * valid
    rbin, cbin = xp.where(valid, rbin, 0.0), xp.where(valid, cbin, 0.0)  # zero weight: any bin in range
    obin = ((xp.degrees(xp.arctan2(dy, dx)) - ori) % 360.0) * (n / 360.0)
    r0, c0, o0 = xp.floor(rbin), xp.floor(cbin), xp.floor(obin)
    fr, fc, fo = rbin - r0, cbin - c0, obin - o0
    r0, c0, o0 = r0.astype(xp.int64), c0.astype(xp.int64), o0.astype(xp.int64)
    size = (d + 2) * (d + 2) * n
    hist = xp.zeros(len(cx) * size, xp.float32)
    base = xp.arange(len(cx))[:, None] * size
    for dr, wr in ((0, 1 - fr), (1, fr)):
        for dc, wc in ((0, 1 - fc), (1, fc)):
            for do, wo in ((0, 1 - fo), (1, fo)):
                index = base + ((r0 + 1 + dr) * (d + 2) + (c0 + 1 + dc)) * n + (o0 + do) % n
                hist += xp.bincount(index.ravel(), weights=(mag * wr * wc * wo).ravel(), minlength=hist.size)
    desc = hist.reshape(len(cx), d + 2, d + 2, n)[:, 1:-1, 1:-1, :].reshape(len(cx), -1)
    desc = desc / xp.maximum(xp.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
    desc = xp.minimum(desc, 0.2)
    return (desc / xp.maximum(xp.linalg.norm(desc, axis=1, keepdims=True), 1e-12)).astype(xp.float32)


def _concat(parts: list[Keypoints], xp: Any, layout: tuple[int, int], max_features: int | None) -> Keypoints:
    d, n = layout
    if not parts:
        z = xp.zeros(0, xp.float32)
        return Keypoints(
            xp.zeros((0, 2), xp.float64),
            z,
            z,
            xp.zeros(0, xp.int32),
            xp.zeros(0, xp.int8),
            z,
            xp.zeros((0, d * d * n), xp.float32),
        )
    fields = {f: xp.concatenate([getattr(p, f) for p in parts]) for f in Keypoints.__dataclass_fields__}
    order = xp.argsort(-fields["response"], kind="stable")
    if max_features is not None:
        order = order[:max_features]
    return Keypoints(**{f: v[order] for f, v in fields.items()})


def tile_margin(
    octaves: int,
    first_octave: int = -1,
    levels: int = 3,
    sigma0: float = 1.6,
    layout: tuple[int, int] = (4, 8),
    assumed_blur: float = 0.5,
) -> int:
    """Input pixels around a tile on which every keypoint of the tile's core depends: the chain of
    Gaussian blurs through the octaves, then the DoG, refinement and descriptor windows."""
    sigmas = [sigma0 * 2.0 ** (s / levels) for s in range(levels + 3)]
    per_octave = sum(math.ceil(3 * math.sqrt(b * b - a * a)) for a, b in zip(sigmas, sigmas[1:], strict=False))
    present = assumed_blur * 2.0 ** (-first_octave)
    base = math.ceil(3 * math.sqrt(max(sigma0**2 - present**2, 0.01)))
    blur = 2.0**first_octave * base + sum(2.0**o * per_octave for o in range(first_octave, first_octave + octaves))
    top = first_octave + octaves - 1
    window = math.ceil(3 * sigmas[-1] * math.sqrt(2.0) * (layout[0] + 1) * 0.5) + MAX_STEPS + 3
    return int(math.ceil(blur + 2.0**top * window)) + 2


def sift_tiled(
    image: Any,
    tile: int,
    octaves: int,
    first_octave: int = -1,
    levels: int = 3,
    sigma0: float = 1.6,
    layout: tuple[int, int] = (4, 8),
    max_features: int | None = None,
    **options: Any,
) -> Keypoints:
    """``sift(image, octaves=octaves, ...)`` computed tile by tile, for images too large for one pass.

    Tiles start on the coarsest octave's pixel grid and carry ``tile_margin`` of context, so every
    keypoint is computed from exactly the pixels the untiled run would use; each is kept by the tile
    whose core holds it. The result equals the untiled one.
    """
    xp = get_array_module(image)
    align = 2 ** max(first_octave + octaves - 1, 0)
    if tile % align:
        raise ValueError(f"tile must be a multiple of {align} px (the coarsest octave's pixel)")
    margin = tile_margin(octaves, first_octave, levels, sigma0, layout)
    margin += -margin % align
    h, w = image.shape[:2]
    parts = []
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            ya, xa = max(y0 - margin, 0), max(x0 - margin, 0)
            found = sift(
                image[ya : min(y0 + tile + margin, h), xa : min(x0 + tile + margin, w)],
                first_octave,
                octaves,
                levels,
                sigma0,
                layout=layout,
                **options,
            )
            x, y = found.xy[:, 0] + xa, found.xy[:, 1] + ya
            core = (x >= x0 - 0.5) & (x < x0 + tile - 0.5) & (y >= y0 - 0.5) & (y < y0 + tile - 0.5)
            fields = {f: getattr(found, f)[core] for f in Keypoints.__dataclass_fields__}
            fields["xy"] = xp.stack([x[core], y[core]], axis=1)
            parts.append(Keypoints(**fields))
    return _concat(parts, xp, layout, max_features)
