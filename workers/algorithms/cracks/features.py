"""The crack detector's per-pixel features: illumination normalisation, a filter bank of thin-dark-line
evidence (Hessian/Frangi, oriented line means) at two resolutions, brightness context, and the auto-context
features of a first probability map (see :mod:`workers.algorithms.cracks.detection` for the whole chain)."""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

HESSIAN_SIGMAS = (1.0, 1.5, 2.0, 3.0, 4.0)
LINE_LENGTHS = (9, 17, 33)
N_ORIENTATIONS = 12
N_BANK = 21  # channels of filter_bank
CONTEXT_LINE_LENGTHS = (17, 33)


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey levels of an (H, W) or (H, W, 3) BGR uint8 image (OpenCV's luma weights)."""
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif image.ndim != 2:
        raise ValueError(f"expected an (H, W) or (H, W, 3) image, got shape {image.shape}")
    return image.astype(np.float32)


def illumination_terms(
    gray: np.ndarray, background_sigma: float = 20.0, contrast_sigma: float = 12.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The large-scale background, and the centred log-ratio to it and its local spread.

    Parameters
    ----------
    gray : (H, W) float32 grey levels.
    background_sigma : Gaussian scale of the shading model, px; much wider than a crack.
    contrast_sigma : scale of the local mean and standard deviation of the log-ratio, px.

    Returns
    -------
    background, centred, spread : (H, W) float32 each; ``centred / spread`` is the local z-score.
    """
    background = cv2.GaussianBlur(gray, (0, 0), background_sigma)
    ratio = np.log((gray + 8.0) / (background + 8.0))  # +8: dark pixels do not explode the log
    centred = ratio - cv2.GaussianBlur(ratio, (0, 0), contrast_sigma)
    spread = np.sqrt(np.maximum(cv2.GaussianBlur(centred**2, (0, 0), contrast_sigma), 0.0)) + 1e-3
    return background, centred.astype(np.float32), spread.astype(np.float32)


def normalise_illumination(
    gray: np.ndarray, background_sigma: float = 20.0, contrast_sigma: float = 12.0
) -> np.ndarray:
    """Remove low-frequency shading, then normalise local contrast (see :func:`illumination_terms`).

    Returns
    -------
    (H, W) float32, ~zero mean and unit standard deviation in every neighbourhood; cracks are negative.
    """
    _, centred, spread = illumination_terms(gray, background_sigma, contrast_sigma)
    return centred / spread


def hessian_eigenvalues(image: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Scale-normalised (sigma^2) Hessian eigenvalues of a Gaussian-smoothed image.

    Returns
    -------
    larger, smaller : (H, W) float32 each, signed; across a dark line ``larger`` is strongly positive.
    """
    smooth = cv2.GaussianBlur(image, (0, 0), sigma)
    s2 = np.float32(sigma * sigma)
    dxx = cv2.Sobel(smooth, cv2.CV_32F, 2, 0, ksize=1) * s2
    dyy = cv2.Sobel(smooth, cv2.CV_32F, 0, 2, ksize=1) * s2
    dxy = cv2.Sobel(smooth, cv2.CV_32F, 1, 1, ksize=3) * (s2 / 4)  # ksize 3 is 4x the central difference
    half_trace = (dxx + dyy) / 2
    root = np.sqrt(((dxx - dyy) / 2) ** 2 + dxy**2)
    return half_trace + root, half_trace - root


def ridge_response(
    norm: np.ndarray, sigmas: tuple[float, ...] = HESSIAN_SIGMAS, beta: float = 0.5, c: float = 0.5
) -> np.ndarray:
    """Multi-scale Frangi vesselness for dark lines (Frangi et al. 1998, eq. 15, sign flipped), max over sigmas.

    Parameters
    ----------
    norm : (H, W) float32, output of :func:`normalise_illumination` (so ``c`` is in z-score units).

    Returns
    -------
    (H, W) float32 in [0, 1).
    """
    out = np.zeros_like(norm)
    for sigma in sigmas:
        across, along = hessian_eigenvalues(norm, sigma)
        blobness = along / np.maximum(across, 1e-6)
        structure = across**2 + along**2
        v = np.exp(-(blobness**2) / (2 * beta**2)) * (1 - np.exp(-structure / (2 * c**2)))
        out = np.maximum(out, np.where(across > 0, v, 0).astype(np.float32))
    return out


@lru_cache(maxsize=8)
def line_kernels(length: int, n_orientations: int = N_ORIENTATIONS) -> tuple[np.ndarray, ...]:
    """Anti-aliased 1-px line segments of ``length`` px through the kernel centre, normalised to sum 1.

    Returns
    -------
    ``n_orientations`` arrays (length, length) float32, orientations k * 180 / n degrees.
    """
    centre = (length - 1) / 2
    kernels = []
    for angle in np.arange(n_orientations) * np.pi / n_orientations:
        kernel = np.zeros((length, length), np.float32)
        d = centre * np.array([np.cos(angle), np.sin(angle)])
        p1, p2 = np.round(centre - d).astype(int), np.round(centre + d).astype(int)
        cv2.line(kernel, (int(p1[0]), int(p1[1])), (int(p2[0]), int(p2[1])), 1.0, 1, cv2.LINE_AA)
        kernels.append(kernel / kernel.sum())
    return tuple(kernels)


def oriented_line_means(image: np.ndarray, length: int) -> np.ndarray:
    """(n_orientations, H, W) float32 mean of ``image`` along segments through each pixel (reflected borders)."""
    return np.stack([cv2.filter2D(image, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT) for k in line_kernels(length)])


def line_mean_extremes(image: np.ndarray, length: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) float32 each: the least and the greatest of :func:`oriented_line_means` over the orientations,
    kept as they come (the (n_orientations, H, W) stack is never held)."""
    darkest = lightest = None
    for kernel in line_kernels(length):
        mean = cv2.filter2D(image, cv2.CV_32F, kernel, borderType=cv2.BORDER_REFLECT)
        if darkest is None or lightest is None:
            darkest, lightest = mean, mean.copy()
            continue
        np.minimum(darkest, mean, out=darkest)
        np.maximum(lightest, mean, out=lightest)
    assert darkest is not None and lightest is not None  # line_kernels has at least one orientation
    return darkest, lightest


def filter_bank(gray: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Thin-dark-line evidence at one resolution.

    Parameters
    ----------
    gray : (H, W) float32 grey levels.
    out : (H, W, 21) float32 to write into (a view of a larger feature array will do); default a new one.

    Returns
    -------
    (H, W, 21) float32: smoothed normalised intensity (sigma 1, 2), Hessian eigenvalue pairs at
    ``HESSIAN_SIGMAS``, gradient magnitude (sigma 1, 2.5), per line length (darkest line mean - box mean, line
    contrast across orientations), Frangi vesselness.
    """
    out = np.empty((*gray.shape, N_BANK), np.float32) if out is None else out
    norm = normalise_illumination(gray)
    channels = iter(range(N_BANK))

    def put(channel: np.ndarray) -> None:  # each channel straight into its place: no list, no stacked copy
        out[..., next(channels)] = channel

    for s in (1.0, 2.0):
        put(cv2.GaussianBlur(norm, (0, 0), s))
    for sigma in HESSIAN_SIGMAS:
        for eigenvalues in hessian_eigenvalues(norm, sigma):
            put(eigenvalues)
    for sigma in (1.0, 2.5):
        smooth = cv2.GaussianBlur(norm, (0, 0), sigma)
        gx, gy = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=1), cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=1)
        put(np.sqrt(gx * gx + gy * gy) * np.float32(sigma))
    fine = cv2.GaussianBlur(norm, (0, 0), 0.7)
    for length in LINE_LENGTHS:
        darkest, lightest = line_mean_extremes(fine, length)
        put(darkest - cv2.blur(fine, (length, length)))
        put(lightest - darkest)
    put(ridge_response(norm))
    return out


def brightness_context(gray: np.ndarray) -> np.ndarray:
    """What the normalised filter bank no longer sees: how bright and how textured the surroundings are.

    Parameters
    ----------
    gray : (H, W) float32 grey levels.

    Returns
    -------
    (H, W, 2) float32: log of the large-scale background over the image's median grey level (a crazed
    painted marking on a road is brighter than the asphalt around it), and log of the local spread of
    :func:`illumination_terms` over its median (how strong the texture a crack must stand out from is).
    """
    background, _, spread = illumination_terms(gray)
    brightness = np.log((background + 8.0) / (float(np.median(gray)) + 8.0))
    texture = np.log(spread / float(np.median(spread)))
    return np.stack([brightness, texture], axis=-1).astype(np.float32)


def pixel_features(image: np.ndarray) -> np.ndarray:
    """The network's input: the filter bank at full and half resolution, and the brightness context.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) BGR uint8.

    Returns
    -------
    (H, W, 44) float32: :func:`filter_bank` of the image (21), of the image halved by area averaging and
    bilinearly upsampled back (21: wider and fainter cracks, twice the context), :func:`brightness_context` (2).
    """
    gray = to_gray(image)
    h, w = gray.shape
    out = np.empty((h, w, 2 * N_BANK + 2), np.float32)
    filter_bank(gray, out[..., :N_BANK])
    half = cv2.resize(gray, (max(w // 2, 1), max(h // 2, 1)), interpolation=cv2.INTER_AREA)
    out[..., N_BANK : 2 * N_BANK] = cv2.resize(filter_bank(half), (w, h), interpolation=cv2.INTER_LINEAR).reshape(
        h, w, -1
    )
    out[..., 2 * N_BANK :] = brightness_context(gray)
    return out


def context_features(probability: np.ndarray) -> np.ndarray:
    """The stage-2 (auto-context) channels of a stage-1 probability map.

    Parameters
    ----------
    probability : (H, W) float32 in [0, 1].

    Returns
    -------
    (H, W, 10) float32: the map, Gaussian blurs (sigma 2, 4, 8), grey dilations (5, 11 px squares), and
    per line length in ``CONTEXT_LINE_LENGTHS`` the max and min over orientations of the mean along a line
    (high max with low min: the pixel continues a crack). The line means run on the map at half
    resolution (a quarter of the time; the map is smooth at that scale) and are upsampled bilinearly.
    """
    p = probability.astype(np.float32)
    h, w = p.shape
    channels = [p] + [cv2.GaussianBlur(p, (0, 0), s) for s in (2.0, 4.0, 8.0)]
    channels += [cv2.dilate(p, np.ones((k, k), np.uint8)) for k in (5, 11)]
    half = cv2.resize(p, ((w + 1) // 2, (h + 1) // 2), interpolation=cv2.INTER_AREA)
    for length in CONTEXT_LINE_LENGTHS:
        means = oriented_line_means(half, length // 2 + 1)
        channels += [
            cv2.resize(m, (w, h), interpolation=cv2.INTER_LINEAR) for m in (means.max(axis=0), means.min(axis=0))
        ]
    return np.stack(channels, axis=-1)
