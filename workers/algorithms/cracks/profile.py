"""Crack widths from the crack's cross-section profile in the image: a blurred line fitted to the darkness
of every pixel near the crack against its signed distance from the crack's centreline.

A crack of width w and contrast C (the share of the coating's brightness it takes away) seen through a
point spread function of Gaussian sigma s darkens a pixel at distance d from its centreline by

    y(d) = b + C / 2 [erf((d - d0 + w / 2) / (sqrt(2) s)) - erf((d - d0 - w / 2) / (sqrt(2) s))],

a box of width w convolved with the PSF (b: what is left of the background, d0: the centreline's offset).
Its area C w is the crack's darkness deficit, whatever the blur; its shape tells C from w as long as the
crack is wider than the blur. Pixels are taken at their exact distance from the (smoothed) skeleton, so
the profile of a crack many pixels long is sampled far finer than the raster (as the slanted-edge
method of ISO 12233 samples an edge); C, w, s, b and d0 are fitted to all of them at once with a robust
loss, so neither the contrast nor the PSF has to be known beforehand.

A crack narrower than that (a couple of photo pixels, or four PSF sigmas) cannot tell C from w: its profile
is the PSF's, or where it runs along the photo's pixels a flat-topped pixel or two. Its deficit C w stays
right, and over the coating's crack contrast, measured on its widest cracks (:func:`reference_contrast`),
it is the crack's equivalent width (:func:`crack_widths`).

Photo pixels are counted across each crack (:func:`sampling_across`): an oblique view's pixel reaches
``1 / sin(elevation)`` times farther along the view than across it, so a crack running across the view is
seen by fewer pixels across it than one running along the view.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy import ndimage as ndi
from scipy.optimize import least_squares
from scipy.spatial import cKDTree
from scipy.special import erf

from workers.algorithms.cracks.geometry import RESOLVED_WIDTH_PX, Crack

DENSE_STEP_PX = 0.25  # spacing of the points the centreline is resampled to, px
MIN_SAMPLES = 60  # fewer pixels near a crack than this: no profile width


@dataclass(frozen=True)
class ProfileFit:
    """A blurred line fitted to a crack's cross-section, raster px (contrast: share of the coating's level)."""

    width_px: float
    contrast: float
    blur_px: float  # Gaussian sigma of the PSF the crack is seen through
    offset_px: float  # of the profile's centre from the centreline, along the normal
    samples: int
    rms: float  # robust residual spread of the darkness, share of the coating's level

    @property
    def deficit_px(self) -> float:
        """The darkness deficit across the crack (contrast x width), px: what any blur leaves unchanged."""
        return self.contrast * self.width_px


def coating_level(grey: np.ndarray, mask: np.ndarray, background_px: float, grow_px: int) -> np.ndarray:
    """(H, W) float32 the coating's local grey level: a Gaussian (``background_px``) average of the pixels
    farther than ``grow_px`` from ``mask``, so neither a crack nor its blurred edges darken it."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow_px + 1, 2 * grow_px + 1))
    free = (cv2.dilate(mask.astype(np.uint8), kernel) == 0).astype(np.float32)
    grey = grey.astype(np.float32)
    return cv2.GaussianBlur(grey * free, (0, 0), background_px) / np.maximum(
        cv2.GaussianBlur(free, (0, 0), background_px), 1e-3
    )


def blurred_line(d: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Darkness (N,) at signed distances ``d`` (N,) px of a line ``params`` = (b, C, d0, w, s), see above."""
    b, c, d0, w, s = params
    scale = np.sqrt(2.0) * s
    return b + 0.5 * c * (erf((d - d0 + w / 2) / scale) - erf((d - d0 - w / 2) / scale))


def _fit(d: np.ndarray, y: np.ndarray, min_blur_px: float) -> tuple[np.ndarray, float]:
    """Least-squares (b, C, d0, w, s) of :func:`blurred_line` to samples (d, y), and the samples' noise."""
    reach = float(np.abs(d).max())
    outer = np.abs(d) > 0.7 * reach
    b0 = float(np.median(y[outer])) if outer.sum() >= 10 else 0.0
    noise = max(float(1.4826 * np.median(np.abs(y[outer] - b0))) if outer.sum() >= 10 else 0.05, 1e-3)
    keys, inverse = np.unique(np.round(d / 0.5).astype(np.int64), return_inverse=True)
    means = np.bincount(inverse, weights=y - b0) / np.bincount(inverse)
    c0 = float(max(means.max(), 1e-3))
    area = float(np.clip(means, 0, None).sum() * 0.5)
    start = np.array([b0, c0, float(keys[int(np.argmax(means))] * 0.5), max(area / c0, 0.3), max(0.6, min_blur_px)])
    lower = np.array([-1.0, 1e-3, -reach / 2, 0.05, min_blur_px])
    upper = np.array([1.0, 2.0, reach / 2, 2 * reach, max(reach / 2, min_blur_px + 0.1)])
    fit = least_squares(
        lambda p: blurred_line(d, p) - y,
        np.clip(start, lower + 1e-6, upper - 1e-6),
        bounds=(lower, upper),
        loss="soft_l1",
        f_scale=noise,
        x_scale=np.array([0.05, 0.1, 0.5, 0.5, 0.2]),
    )
    return fit.x, noise


def _local_offsets(
    d: np.ndarray, y: np.ndarray, along: np.ndarray, params: np.ndarray, noise: float, chunk: int
) -> np.ndarray:
    """(M,) the centreline's offset at each sample: per stretch of ``chunk`` centreline points, the shift of
    the fitted profile that fits that stretch best (a grid search, clipped residuals), smoothed along."""
    shifts = np.arange(-1.5, 1.5001, 0.05)
    keys, inverse = np.unique(along // chunk, return_inverse=True)
    cost = np.empty((len(keys), len(shifts)))
    for k, shift in enumerate(shifts):
        shifted = params.copy()
        shifted[2] += shift
        r2 = np.minimum((blurred_line(d, shifted) - y) ** 2, (3 * noise) ** 2)
        cost[:, k] = np.bincount(inverse, weights=r2, minlength=len(keys))
    best = params[2] + shifts[np.argmin(cost, axis=1)]
    return ndi.gaussian_filter1d(best, 1.0, mode="nearest")[inverse]


def fit_blurred_line(
    d: np.ndarray,
    y: np.ndarray,
    *,
    along: np.ndarray | None = None,
    min_blur_px: float = 0.25,
    chunk_px: float = 8.0,
    rounds: int = 2,
) -> ProfileFit | None:
    """Fit :func:`blurred_line` to darkness samples ``y`` (N,) at signed distances ``d`` (N,) px.

    Least squares with a soft-L1 loss (the coating's grain and a neighbouring crack are outliers), started
    from the profile's moments. With ``along`` (N,) int (:func:`cross_section`), the centreline's offset is
    then found per ``chunk_px`` of crack and taken out, and the line fitted again (``rounds`` times): a
    skeleton's staircase leaves the centreline a fraction of a pixel off, which would read as blur.
    Returns None with fewer than ``MIN_SAMPLES`` samples.
    """
    if len(d) < MIN_SAMPLES:
        return None
    params, noise = _fit(d, y, min_blur_px)
    shift = np.zeros_like(d)
    chunk = max(1, int(round(chunk_px / DENSE_STEP_PX)))
    if along is not None:
        for _ in range(rounds):
            shift = _local_offsets(d, y, along, params, noise, chunk)
            params, noise = _fit(d - shift, y, min_blur_px)
    residual = blurred_line(d - shift, params) - y
    rms = float(1.4826 * np.median(np.abs(residual - np.median(residual))))
    _, c, d0, w, s = params
    return ProfileFit(float(w), float(c), float(s), float(d0), len(d), rms)


def _dense_branch(points: np.ndarray, trim_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A branch (N, 2) (x, y) px resampled every ``DENSE_STEP_PX``: points (M, 2), unit normals (M, 2), and
    (M,) bool, the points farther than ``trim_px`` along it from both its ends (a tip's cap, or another
    branch at a junction, would widen the profile)."""
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    along = np.r_[0.0, np.cumsum(steps)]
    s = np.linspace(0.0, along[-1], max(2, int(np.ceil(along[-1] / DENSE_STEP_PX)) + 1))
    dense = np.column_stack([np.interp(s, along, points[:, 0]), np.interp(s, along, points[:, 1])])
    tangent = np.gradient(ndi.gaussian_filter1d(dense, 4.0, axis=0, mode="nearest"), axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    return dense, normal, (s > trim_px) & (s < along[-1] - trim_px)


def cross_section(
    darkness: np.ndarray, paths_px: Sequence[np.ndarray], usable: np.ndarray, reach_px: float, trim_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The darkness of every usable pixel within ``reach_px`` of a crack against its signed distance from the
    crack's centreline.

    Parameters
    ----------
    darkness : (H, W) float32, ``1 - grey / coating level``.
    paths_px : the crack's branches, each (N, 2) float64 (x, y) px, ordered.
    usable : (H, W) bool, pixels that may be sampled (seen, not on another crack).
    reach_px : half-width of the strip sampled across the crack, px.
    trim_px : stretch of each branch's ends left out, px.

    Returns
    -------
    d : (M,) float64 signed distance from the centreline, px.
    y : (M,) float64 darkness there.
    along : (M,) int64 where along the crack: index of the nearest centreline point, ``DENSE_STEP_PX`` apart.
    """
    parts = [_dense_branch(p, trim_px) for p in paths_px if len(p) > 1]
    if not parts:
        return np.zeros(0), np.zeros(0), np.zeros(0, np.int64)
    dense, normal, inner = (np.concatenate(a) for a in zip(*parts, strict=True))
    h, w = darkness.shape
    r = int(np.ceil(reach_px))
    x0, y0 = np.maximum(np.floor(dense.min(axis=0)).astype(int) - r, 0)
    x1, y1 = np.minimum(np.ceil(dense.max(axis=0)).astype(int) + r, [w - 1, h - 1])
    strip = np.zeros((y1 - y0 + 1, x1 - x0 + 1), np.uint8)
    cells = np.rint(dense - [x0, y0]).astype(int)
    strip[cells[:, 1], cells[:, 0]] = 1
    strip = cv2.dilate(strip, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    rows, cols = np.nonzero(strip.astype(bool) & usable[y0 : y1 + 1, x0 : x1 + 1])
    pixels = np.column_stack([cols + x0, rows + y0]).astype(np.float64)
    distance, nearest = cKDTree(dense).query(pixels, distance_upper_bound=reach_px + 1.0)
    keep = np.isfinite(distance)
    keep[keep] = inner[nearest[keep]]
    pixels, nearest = pixels[keep], nearest[keep]
    d = np.einsum("ij,ij->i", pixels - dense[nearest], normal[nearest])
    close = np.abs(d) <= reach_px
    y = darkness[pixels[close, 1].astype(int), pixels[close, 0].astype(int)]
    return d[close], y.astype(np.float64), nearest[close].astype(np.int64)


def _nearest_to(labels: np.ndarray, label: int, points: np.ndarray, margin: int) -> np.ndarray:
    """(H, W) bool: the pixels within ``margin`` of the box of ``points`` (N, 2) (x, y) px that lie nearer to
    crack ``label`` of ``labels`` (H, W) int than to any other (a neighbour's profile is not this one's)."""
    h, w = labels.shape
    x0, y0 = np.maximum(np.floor(points.min(axis=0)).astype(int) - margin, 0)
    x1, y1 = np.minimum(np.ceil(points.max(axis=0)).astype(int) + margin, [w - 1, h - 1])
    crop = labels[y0 : y1 + 1, x0 : x1 + 1]
    nearest = ndi.distance_transform_edt(crop == 0, return_distances=False, return_indices=True)
    out = np.zeros(labels.shape, bool)
    out[y0 : y1 + 1, x0 : x1 + 1] = crop[nearest[0], nearest[1]] == label
    return out


def profile_widths(
    grey: np.ndarray,
    mask: np.ndarray,
    paths_px: Sequence[Sequence[np.ndarray]],
    *,
    seen: np.ndarray | None = None,
    background_px: float = 8.0,
    min_blur_px: float = 0.25,
    grow_px: int = 3,
) -> list[ProfileFit | None]:
    """A :class:`ProfileFit` per crack (None where too little of it can be sampled).

    Parameters
    ----------
    grey : (H, W) float32 grey levels.
    mask : (H, W) bool, the detector's crack pixels (where they are; not how wide).
    paths_px : per crack, its branches, each (N, 2) float64 (x, y) px (``Crack.paths_mm / mm_per_px``).
    seen : (H, W) bool, the pixels the photos see (default: all).
    background_px : Gaussian scale of the coating's local level, px (:func:`coating_level`).
    min_blur_px : the least PSF sigma the raster can have, px (the photo's pixel, resampled).
    grow_px : pixels this close to ``mask`` are left out of the coating's level (a crack's blurred edges).
    """
    if grey.shape != mask.shape:
        raise ValueError(f"grey {grey.shape} and mask {mask.shape} differ in shape")
    mask = mask.astype(bool)
    if not mask.any():
        return [None] * len(paths_px)
    level = coating_level(grey, mask, background_px, grow_px)
    darkness = (1.0 - grey / np.maximum(level, 1.0)).astype(np.float32)
    labels, _ = ndi.label(mask, structure=np.ones((3, 3), bool))
    radius = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    seen = np.ones(mask.shape, bool) if seen is None else seen.astype(bool)
    samples: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] = []
    for paths in paths_px:
        points = np.concatenate([np.asarray(p, dtype=np.float64) for p in paths])
        cells = np.rint(points).astype(int)
        inside = (cells >= 0).all(axis=1) & (cells[:, 0] < mask.shape[1]) & (cells[:, 1] < mask.shape[0])
        own = labels[cells[inside, 1], cells[inside, 0]]
        if not (own > 0).any():
            samples.append(None)
            continue
        label = int(np.bincount(own[own > 0]).argmax())
        r = float(np.median(radius[cells[inside, 1], cells[inside, 0]]))
        reach, trim = max(6.0, 3 * r + 4), max(3.0, 2 * r + 2)
        usable = _nearest_to(labels, label, points, int(np.ceil(reach)) + 2) & seen
        samples.append(cross_section(darkness, paths, usable, reach, trim))
    return [None if s is None else fit_blurred_line(s[0], s[1], along=s[2], min_blur_px=min_blur_px) for s in samples]


RESOLVED_PHOTO_PX = 2.5  # a profile tells its own contrast from its width past this many photo pixels ...
RESOLVED_BLURS = 4.0  # ... and this many of its PSF sigmas (an oblique view blurs some directions more)
MEASURED_BLURS = 2.5  # a profile narrower than this many PSF sigmas is the PSF's, whatever the pixels
LINE_ASPECT = 10.0  # a crack runs at least this many times as far as its profile is wide


def resolved(fit: ProfileFit, photo_px: float) -> bool:
    """Whether the photos resolve a crack's profile: its fitted width is at least ``RESOLVED_PHOTO_PX`` photo
    pixels (``photo_px``: one photo pixel across the crack, in raster px) and ``RESOLVED_BLURS`` PSF sigmas,
    with a contrast a crack can have (at most 1)."""
    return fit.width_px >= max(RESOLVED_PHOTO_PX * photo_px, RESOLVED_BLURS * fit.blur_px) and fit.contrast <= 1.0


def line_like(fit: ProfileFit | None, length_px: float, mask_width_px: float) -> bool:
    """Whether a crack ``length_px`` long with profile ``fit`` is a line: at least ``LINE_ASPECT`` times as
    long as its profile is wide (its width and 2.5 blur sigmas, in the same px; without a fit, a crack too
    short to sample across, its mask's mean width ``mask_width_px``). A shorter dark mark is a blot of the
    coating's grain, wide and faint, or a smudge far blurrier than the photo: on rendered coatings 1.3-7
    times as long as wide, against 25 and more for cracks of 18 mm and longer."""
    width = mask_width_px if fit is None else fit.width_px + 2.5 * fit.blur_px
    return length_px >= LINE_ASPECT * width


def reference_contrast(
    fits: Sequence[Sequence[ProfileFit | None]],
    photo_px: Sequence[Sequence[float]],
    lengths_px: Sequence[Sequence[float]],
) -> float | None:
    """The coating's crack contrast: the length-weighted median contrast of the cracks of every image
    ``fits[i]`` (for instance every load step of one specimen) at least ``RESOLVED_WIDTH_PX`` photo pixels
    and ``MEASURED_BLURS`` PSF sigmas wide, whose profiles tell contrast from width to some 10 % (narrower
    ones trade contrast for width and read as faint wide lines); None if there is none.
    ``photo_px[i][k]``: one photo pixel across crack ``k`` of image ``i``, raster px; ``lengths_px[i][k]``:
    its length, raster px.

    The cracks of one coating take away about the same share of the light once wide enough to show it, and
    a ratio to the coating's own level does not change with exposure between load steps.
    """
    if not len(fits) == len(photo_px) == len(lengths_px):
        raise ValueError(f"{len(fits)} images of fits but {len(photo_px)} of samplings, {len(lengths_px)} of lengths")
    measured = [
        (f.contrast, length)
        for image, pxs, lengths in zip(fits, photo_px, lengths_px, strict=True)
        for f, px, length in zip(image, pxs, lengths, strict=True)
        if f is not None and f.width_px >= max(RESOLVED_WIDTH_PX * px, MEASURED_BLURS * f.blur_px) and f.contrast <= 1
    ]
    if not measured:
        return None
    contrast, weight = np.array(sorted(measured)).T
    return float(contrast[np.searchsorted(np.cumsum(weight), 0.5 * weight.sum())])


def crack_widths(fits: Sequence[ProfileFit | None], photo_px: Sequence[float], contrast: float | None) -> np.ndarray:
    """(K,) float64 each crack's width, px (NaN: no fit), from its profile fit.

    A crack the photos resolve (:func:`resolved`, ``photo_px[k]``: one photo pixel across crack ``k``, raster
    px) keeps its own fit. A narrower one's profile does not tell its contrast from its width: through the
    blur it takes the PSF's shape, and where it runs along the photo's pixels (at a phase that stays the same
    for long stretches) the flat top of a pixel or two; what stays right is its darkness deficit. Its width
    is its equivalent width, that deficit over ``contrast`` (:func:`reference_contrast`). Without a contrast,
    the own fits are all there is.
    """
    if len(photo_px) != len(fits):
        raise ValueError(f"{len(fits)} fits but {len(photo_px)} photo samplings")
    if any(px <= 0 for px in photo_px):
        raise ValueError("photo samplings must be positive")
    widths = np.full(len(fits), np.nan)
    for k, (f, px) in enumerate(zip(fits, photo_px, strict=True)):
        if f is not None:
            widths[k] = f.width_px if contrast is None or resolved(f, px) else f.deficit_px / contrast
    return widths


def sampling_across(paths_mm: Sequence[np.ndarray], footprint: np.ndarray, footprint_mm_per_px: float) -> float | None:
    """The photos' sampling across a crack, mm per photo pixel: the median over its centreline of
    ``sqrt(n^T F n)``, ``n`` the centreline's unit normal and ``F`` the photo pixel's footprint there
    (``specimen.photo_footprint``, (h, w, 3) on a raster of ``footprint_mm_per_px``, nearest node). None
    where no photo sees the crack."""
    values = []
    for path in paths_mm:
        if len(path) < 2:
            continue
        tangent = np.gradient(ndi.gaussian_filter1d(np.asarray(path, np.float64), 2.0, axis=0, mode="nearest"), axis=0)
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
        cells = np.rint(path / footprint_mm_per_px).astype(int)
        cols = np.clip(cells[:, 0], 0, footprint.shape[1] - 1)
        rows = np.clip(cells[:, 1], 0, footprint.shape[0] - 1)
        fxx, fxy, fyy = (footprint[rows, cols, i].astype(np.float64) for i in range(3))
        nx, ny = -tangent[:, 1], tangent[:, 0]
        across = nx * nx * fxx + 2 * nx * ny * fxy + ny * ny * fyy
        values.append(np.sqrt(across[fxx > 0]))
    joined = np.concatenate(values) if values else np.zeros(0)
    return float(np.median(joined)) if len(joined) else None


def with_widths(cracks: Sequence[Crack], widths_mm: np.ndarray) -> list[Crack]:
    """``cracks`` with mean widths ``widths_mm`` (K,) (NaN: keep the crack's), each maximum scaled alike."""
    out = []
    for crack, width in zip(cracks, np.asarray(widths_mm, dtype=np.float64), strict=True):
        if not np.isfinite(width) or crack.mean_width_mm <= 0:
            out.append(crack)
            continue
        ratio = float(width) / crack.mean_width_mm
        out.append(
            replace(crack, mean_width_mm=float(width), max_width_mm=max(float(width), crack.max_width_mm * ratio))
        )
    return out


def isotropic_sampling(footprint: np.ndarray) -> np.ndarray:
    """(M,) float64 the photos' isotropic sampling, mm per photo pixel (``det(F) ** 0.25``), at every point of a
    ``specimen.photo_footprint`` (h, w, 3) that a photo sees."""
    fxx, fxy, fyy = (footprint[..., i].astype(np.float64) for i in range(3))
    seen = fxx > 0
    return (np.maximum(fxx * fyy - fxy * fxy, 0.0)[seen]) ** 0.25
