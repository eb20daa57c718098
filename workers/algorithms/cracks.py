"""Crack detection on orthorectified photos of a coating: thin dark lines on a textured, unevenly lit surface.

The chain, per image:

1. illumination normalisation: log-ratio to a large-scale background (removes the shading of light at
   30-60 degrees), then a local z-score (local contrast normalisation);
2. a filter bank of thin-dark-line evidence: multi-scale Hessian eigenvalues and the Frangi measure
   (Frangi et al., MICCAI 1998), oriented line means over 12 directions at three lengths minus the
   window mean (the line operator of Ricci & Perfetti, IEEE TMI 2007), gradient magnitude and smoothed
   intensity; computed on the image and on the image halved (wider, fainter cracks), plus two channels of
   brightness and texture context;
3. two classifiers whose probabilities are averaged: a two-stage per-pixel classifier on the full-resolution
   filter bank (a one-hidden-layer MLP, then a second one that also sees the first's probability map
   blurred, dilated and averaged along lines: auto-context, Tu & Bai, PAMI 2010), and a small U-Net
   (19k weights, three resolutions, :class:`CrackNet`) on all the channels. Their weights
   ``crack_model.npz`` (96 kB) are trained by ``scripts/train_crack_model.py`` on CrackForest images
   001-040 (Shi et al., T-ITS 2016), the U-Net in PyTorch; inference here is NumPy/OpenCV only;
4. hysteresis thresholding and removal of components shorter than a minimum extent.

Pixel F1 with a 2-px tolerance (:func:`tolerance_counts`), pooled over images. Cross-validation on 001-040
(4 folds of consecutive images): 0.893 (precision 0.896, recall 0.890), 0.889 with each fold's thresholds
chosen on the other folds; the auto-context MLPs alone scored 0.875-0.885 there. Held-out 041-060, never
used to fit or choose anything: precision 0.830, recall 0.715, F1 0.768 (the MLPs alone: 0.755). Image
042's mask shows a crack that is not in the photo: a detector-free audit of all 60 labels (median darkening
of the labelled pixels against the road around them: 4-19% for 59 images, -0.3% for 042; see
``tests/unit/test_cracks.py``) singles it out; on the 19 held-out images whose labels pass, precision 0.873,
recall 0.761, F1 0.813. 041-060 hold fainter cracks and coarser labels than 001-040.

A first candidate, the U-Net alone without augmentation, scored higher in cross-validation (0.896) but
lower held out (0.723, P 0.683, R 0.767). After that look, the held-out folds of 001-040 were also scored
under exposure, contrast, scale, blur, JPEG and noise changes: the U-Net's precision collapsed on folds
shown 1.33x larger or blurred, the MLPs' did not. The scale and blur augmentation and the average of both
were chosen on those stressed folds (best mean and best worst case).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage as ndi

MODEL_FILE = Path(__file__).with_name("crack_model.npz")
FEATURE_VERSION = 3  # bump when pixel_features or the network change: old weights then refuse to load
HESSIAN_SIGMAS = (1.0, 1.5, 2.0, 3.0, 4.0)
LINE_LENGTHS = (9, 17, 33)
N_ORIENTATIONS = 12
N_BANK = 21  # channels of filter_bank
CONTEXT_LINE_LENGTHS = (17, 33)
# The network's convolutions in the order they run: (name, kernel size, dilation). Their widths are read
# off the weights. See :meth:`CrackNet.logits` for how they are wired.
NET_LAYERS = (("enc0", 1, 1), ("enc1", 3, 1), ("half0", 3, 1), ("half1", 3, 2), ("quarter0", 3, 1),
              ("quarter1", 3, 2), ("quarter2", 3, 4), ("up_half", 3, 1), ("up_full", 3, 1), ("head", 1, 1))
_DILATION = {name: dilation for name, _, dilation in NET_LAYERS}
_EIGHT = np.ones((3, 3), dtype=bool)


@dataclass(frozen=True)
class PixelMLP:
    """One-hidden-layer perceptron (ReLU, sigmoid output) applied to every pixel's feature vector.

    ``mean``/``scale`` (F,) standardise the features; ``w1`` (F, K), ``b1`` (K,), ``w2`` (K,), ``b2`` ().
    """

    mean: np.ndarray
    scale: np.ndarray
    w1: np.ndarray
    b1: np.ndarray
    w2: np.ndarray
    b2: np.ndarray

    def predict(self, features: np.ndarray) -> np.ndarray:
        """Probability (..., ) float32 for features (..., F) float32."""
        if features.shape[-1] != self.mean.shape[0]:
            raise ValueError(f"model expects {self.mean.shape[0]} features, got {features.shape[-1]}")
        x = (features.reshape(-1, features.shape[-1]) - self.mean) / self.scale
        hidden = np.maximum(x @ self.w1 + self.b1, 0.0)
        z = np.clip(hidden @ self.w2 + self.b2, -30.0, 30.0)
        return (1.0 / (1.0 + np.exp(-z))).astype(np.float32).reshape(features.shape[:-1])


def conv2d(x: np.ndarray, weight: np.ndarray, bias: np.ndarray, dilation: int = 1) -> np.ndarray:
    """'Same' 2-D convolution with zero padding, as ``torch.nn.Conv2d(padding=dilation * (k // 2))``.

    Parameters
    ----------
    x : (H, W, Cin) float32.
    weight : (k, k, Cin, Cout) float32, k odd; cross-correlation, as in every deep-learning framework.
    bias : (Cout,) float32.
    dilation : spacing of the kernel taps, px.

    Returns
    -------
    (H, W, Cout) float32. Computed as k * k matrix products summed at their shifts, which is faster than
    ``cv2.filter2D`` per channel pair for the 8-44 channels used here.
    """
    k, cin, cout = weight.shape[0], weight.shape[2], weight.shape[3]
    if x.shape[2] != cin:
        raise ValueError(f"convolution expects {cin} channels, got {x.shape[2]}")
    h, w = x.shape[:2]
    if k == 1:
        return (x.reshape(h * w, cin) @ weight[0, 0] + bias).reshape(h, w, cout)
    r = dilation * (k // 2)
    padded = np.pad(x, ((r, r), (r, r), (0, 0)))
    rows = padded.reshape(-1, cin)
    out = np.empty((h, w, cout), np.float32)
    out[:] = bias
    for i in range(k):
        for j in range(k):
            # each tap's product over the whole padded image, then its shifted window: the copies are of
            # Cout channels, not Cin
            tap = (rows @ weight[i, j]).reshape(padded.shape[0], padded.shape[1], cout)
            out += tap[i * dilation:i * dilation + h, j * dilation:j * dilation + w]
    return out


def avg_pool2(x: np.ndarray) -> np.ndarray:
    """(H / 2, W / 2, C) mean of 2 x 2 blocks of (H, W, C), H and W even (``torch.nn.functional.avg_pool2d(x, 2)``)."""
    h, w, c = x.shape
    return x.reshape(h // 2, 2, w // 2, 2, c).mean(axis=(1, 3), dtype=np.float32)


def upsample2(x: np.ndarray) -> np.ndarray:
    """(2H, 2W, C) bilinear doubling of (H, W, C) with half-pixel centres and clamped edges, as
    ``torch.nn.functional.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)``."""
    for axis in (0, 1):
        n = x.shape[axis]
        before = np.take(x, np.r_[0, 0:n - 1], axis=axis)
        after = np.take(x, np.r_[1:n, n - 1], axis=axis)
        pair = np.stack([0.75 * x + 0.25 * before, 0.75 * x + 0.25 * after], axis=axis + 1)
        shape = list(x.shape)
        shape[axis] = 2 * n
        x = pair.reshape(shape)
    return x.astype(np.float32, copy=False)


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0.0, out=x)


@dataclass(frozen=True)
class CrackNet:
    """A small U-Net (Ronneberger et al., MICCAI 2015) over :func:`pixel_features`, three resolutions deep.

    ``mean``/``scale`` (F,) standardise the features; ``layers`` maps each name of ``NET_LAYERS`` to its
    (k, k, Cin, Cout) float32 weight and (Cout,) float32 bias.
    """

    mean: np.ndarray
    scale: np.ndarray
    layers: dict[str, tuple[np.ndarray, np.ndarray]]

    def _conv(self, name: str, x: np.ndarray, relu: bool = True) -> np.ndarray:
        y = conv2d(x, *self.layers[name], dilation=_DILATION[name])
        return _relu(y) if relu else y

    def logits(self, features: np.ndarray) -> np.ndarray:
        """(H, W) float32 crack logit of (H, W, F) float32 features, H and W multiples of 4.

        Full resolution: a 1x1 then a 3x3 convolution; half (2x2 means): two 3x3 (dilation 1, 2); quarter:
        three 3x3 (dilation 1, 2, 4); then back up, each level concatenated with the bilinearly doubled level
        below and convolved (3x3), and a 1x1 head. ReLU after every convolution but the head. A logit sees
        ~45 px to each side (on top of the features' own reach), so it can tell a crack that continues
        from an isolated dark speck.
        """
        if features.shape[-1] != self.mean.shape[0]:
            raise ValueError(f"network expects {self.mean.shape[0]} features, got {features.shape[-1]}")
        if features.shape[0] % 4 or features.shape[1] % 4:
            raise ValueError(f"network input sides must be multiples of 4, got {features.shape[:2]}")
        full = self._conv("enc1", self._conv("enc0", (features - self.mean) / self.scale))
        half = self._conv("half1", self._conv("half0", avg_pool2(full)))
        quarter = self._conv("quarter2", self._conv("quarter1", self._conv("quarter0", avg_pool2(half))))
        half = self._conv("up_half", np.concatenate([half, upsample2(quarter)], axis=-1))
        full = self._conv("up_full", np.concatenate([full, upsample2(half)], axis=-1))
        return self._conv("head", full, relu=False)[..., 0]

    def predict(self, features: np.ndarray) -> np.ndarray:
        """(H, W) float32 crack probability of (H, W, F) features of any size (reflect-padded to multiples of 4)."""
        h, w = features.shape[:2]
        padded = np.pad(features, ((0, -h % 4), (0, -w % 4), (0, 0)), mode="reflect")
        z = np.clip(self.logits(padded.astype(np.float32, copy=False))[:h, :w], -30.0, 30.0)
        return (1.0 / (1.0 + np.exp(-z))).astype(np.float32)


@dataclass(frozen=True)
class CrackModel:
    """Both classifiers and the post-processing parameters tuned with them (on training images only).

    ``stage1``/``stage2``: the auto-context pair of per-pixel MLPs on the full-resolution filter bank (the
    first ``N_BANK`` feature channels); ``net``: the U-Net on all of :func:`pixel_features`. The crack
    probability is the mean of ``stage2``'s and ``net``'s.
    """

    stage1: PixelMLP
    stage2: PixelMLP
    net: CrackNet
    low: float  # hysteresis: pixels above this join a crack if connected to one above ``high``
    high: float
    min_length_px: float  # components whose bounding-box diagonal is shorter are dropped

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Flat dict of arrays for ``np.savez`` (no pickle)."""
        out: dict[str, np.ndarray] = {"feature_version": np.array(FEATURE_VERSION),
                                      "net_mean": self.net.mean.astype(np.float32),
                                      "net_scale": self.net.scale.astype(np.float32)}
        for name, mlp in (("stage1", self.stage1), ("stage2", self.stage2)):
            for field in ("mean", "scale", "w1", "b1", "w2", "b2"):
                out[f"{name}_{field}"] = np.asarray(getattr(mlp, field), dtype=np.float32)
        for name, (weight, bias) in self.net.layers.items():
            out[f"net_{name}_weight"], out[f"net_{name}_bias"] = weight.astype(np.float32), bias.astype(np.float32)
        for field in ("low", "high", "min_length_px"):
            out[field] = np.array(getattr(self, field), dtype=np.float64)
        return out

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> CrackModel:
        """Inverse of :meth:`to_arrays`; raises ``ValueError`` for weights of another feature version."""
        if int(arrays["feature_version"]) != FEATURE_VERSION:
            raise ValueError(f"crack model has feature version {int(arrays['feature_version'])}, "
                             f"code expects {FEATURE_VERSION}: retrain with scripts/train_crack_model.py")

        def f32(key: str) -> np.ndarray:
            return np.asarray(arrays[key], dtype=np.float32)

        stages = [PixelMLP(*(f32(f"{name}_{field}") for field in ("mean", "scale", "w1", "b1", "w2", "b2")))
                  for name in ("stage1", "stage2")]
        layers = {name: (f32(f"net_{name}_weight"), f32(f"net_{name}_bias")) for name, _, _ in NET_LAYERS}
        net = CrackNet(f32("net_mean"), f32("net_scale"), layers)
        return cls(stages[0], stages[1], net, float(arrays["low"]), float(arrays["high"]),
                   float(arrays["min_length_px"]))


@lru_cache(maxsize=4)
def load_crack_model(path: Path = MODEL_FILE) -> CrackModel:
    """The trained model stored at ``path`` (an ``.npz`` written from :meth:`CrackModel.to_arrays`)."""
    with np.load(path, allow_pickle=False) as data:
        return CrackModel.from_arrays(dict(data))


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey levels of an (H, W) or (H, W, 3) BGR uint8 image (OpenCV's luma weights)."""
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif image.ndim != 2:
        raise ValueError(f"expected an (H, W) or (H, W, 3) image, got shape {image.shape}")
    return image.astype(np.float32)


def illumination_terms(gray: np.ndarray, background_sigma: float = 20.0, contrast_sigma: float = 12.0
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


def normalise_illumination(gray: np.ndarray, background_sigma: float = 20.0,
                           contrast_sigma: float = 12.0) -> np.ndarray:
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


def ridge_response(norm: np.ndarray, sigmas: tuple[float, ...] = HESSIAN_SIGMAS, beta: float = 0.5,
                   c: float = 0.5) -> np.ndarray:
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


def filter_bank(gray: np.ndarray) -> np.ndarray:
    """Thin-dark-line evidence at one resolution.

    Parameters
    ----------
    gray : (H, W) float32 grey levels.

    Returns
    -------
    (H, W, 21) float32: smoothed normalised intensity (sigma 1, 2), Hessian eigenvalue pairs at
    ``HESSIAN_SIGMAS``, gradient magnitude (sigma 1, 2.5), per line length (darkest line mean - box mean, line
    contrast across orientations), Frangi vesselness.
    """
    norm = normalise_illumination(gray)
    channels = [cv2.GaussianBlur(norm, (0, 0), s) for s in (1.0, 2.0)]
    for sigma in HESSIAN_SIGMAS:
        channels.extend(hessian_eigenvalues(norm, sigma))
    for sigma in (1.0, 2.5):
        smooth = cv2.GaussianBlur(norm, (0, 0), sigma)
        gx, gy = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=1), cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=1)
        channels.append(np.sqrt(gx * gx + gy * gy) * np.float32(sigma))
    fine = cv2.GaussianBlur(norm, (0, 0), 0.7)
    for length in LINE_LENGTHS:
        means = oriented_line_means(fine, length)
        darkest, lightest = means.min(axis=0), means.max(axis=0)
        channels += [darkest - cv2.blur(fine, (length, length)), lightest - darkest]
    channels.append(ridge_response(norm))
    return np.stack(channels, axis=-1).astype(np.float32)


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
    half = cv2.resize(gray, (max(w // 2, 1), max(h // 2, 1)), interpolation=cv2.INTER_AREA)
    coarse = cv2.resize(filter_bank(half), (w, h), interpolation=cv2.INTER_LINEAR).reshape(h, w, -1)
    return np.concatenate([filter_bank(gray), coarse, brightness_context(gray)], axis=-1)


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
        channels += [cv2.resize(m, (w, h), interpolation=cv2.INTER_LINEAR) for m in (means.max(axis=0),
                                                                                     means.min(axis=0))]
    return np.stack(channels, axis=-1)


def crack_probability(image: np.ndarray, model: CrackModel | None = None) -> np.ndarray:
    """Per-pixel crack probability.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) BGR uint8, the orthorectified surface.
    model : trained weights; default the committed ``crack_model.npz``.

    Returns
    -------
    (H, W) float32 in [0, 1].
    """
    return features_probability(pixel_features(image), model or load_crack_model())


def features_probability(features: np.ndarray, model: CrackModel) -> np.ndarray:
    """(H, W) float32 crack probability from (H, W, F) :func:`pixel_features`: the mean of the auto-context
    MLPs' (on the first ``N_BANK`` channels) and the network's (on all)."""
    bank = features[..., :N_BANK]
    auto_context = model.stage2.predict(np.concatenate([bank, context_features(model.stage1.predict(bank))], axis=-1))
    return (auto_context + model.net.predict(features)) / 2


def hysteresis_threshold(score: np.ndarray, low: float, high: float) -> np.ndarray:
    """(H, W) bool: 8-connected regions of ``score > low`` that contain a pixel ``score > high`` (Canny 1986)."""
    if low > high:
        raise ValueError(f"low threshold {low} is above high threshold {high}")
    labels, n = ndi.label(score > low, structure=_EIGHT)
    keep = np.zeros(n + 1, dtype=bool)
    keep[np.unique(labels[score > high])] = True
    keep[0] = False
    return keep[labels]


def remove_short_components(mask: np.ndarray, min_length_px: float) -> np.ndarray:
    """(H, W) bool: ``mask`` without the 8-connected components whose bounding-box diagonal < ``min_length_px``.

    The extent, not the area, is tested so that long 1-px cracks survive while compact blobs do not.
    """
    labels, n = ndi.label(mask, structure=_EIGHT)
    keep = np.zeros(n + 1, dtype=bool)
    for index, box in enumerate(ndi.find_objects(labels), start=1):
        if box is not None:
            keep[index] = np.hypot(box[0].stop - box[0].start, box[1].stop - box[1].start) >= min_length_px
    return keep[labels]


def detect_cracks(image: np.ndarray, *, low: float | None = None, high: float | None = None,
                  min_length_px: float | None = None, model: CrackModel | None = None) -> np.ndarray:
    """Crack mask of an orthorectified surface image.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) BGR uint8.
    low, high : hysteresis thresholds on the probability; default the values tuned with the model.
    min_length_px : drop components with a shorter bounding-box diagonal, px; default tuned with the model.
    model : trained weights; default the committed ``crack_model.npz``.

    Returns
    -------
    (H, W) bool, True on crack pixels.
    """
    model = model or load_crack_model()
    probability = crack_probability(image, model)
    mask = hysteresis_threshold(probability, model.low if low is None else low, model.high if high is None else high)
    return remove_short_components(mask, model.min_length_px if min_length_px is None else min_length_px)


@dataclass(frozen=True)
class ToleranceCounts:
    """Pixel counts of a tolerant comparison of a predicted and a true crack mask (sum them over images)."""

    predicted_hit: int  # predicted pixels with a true pixel within the tolerance
    predicted: int
    truth_hit: int  # true pixels with a predicted pixel within the tolerance
    truth: int

    def __add__(self, other: ToleranceCounts) -> ToleranceCounts:
        return ToleranceCounts(self.predicted_hit + other.predicted_hit, self.predicted + other.predicted,
                               self.truth_hit + other.truth_hit, self.truth + other.truth)

    @property
    def precision(self) -> float:
        return self.predicted_hit / self.predicted if self.predicted else 0.0

    @property
    def recall(self) -> float:
        return self.truth_hit / self.truth if self.truth else 0.0

    @property
    def f1(self) -> float:
        p, r = self.precision, self.recall
        return 2 * p * r / (p + r) if p + r > 0 else 0.0


def tolerance_counts(predicted: np.ndarray, truth: np.ndarray, tolerance_px: float = 2.0) -> ToleranceCounts:
    """Compare two (H, W) bool masks with a distance tolerance (the CrackForest evaluation, Shi et al. 2016).

    A predicted pixel counts as correct if a true pixel lies within ``tolerance_px`` (Euclidean, between
    pixel centres), and a true pixel as found if a predicted pixel does.
    """
    if predicted.shape != truth.shape:
        raise ValueError(f"mask shapes differ: {predicted.shape} vs {truth.shape}")

    def distance_to(mask: np.ndarray) -> np.ndarray:
        return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)

    predicted, truth = predicted.astype(bool), truth.astype(bool)
    return ToleranceCounts(int((distance_to(truth)[predicted] <= tolerance_px).sum()), int(predicted.sum()),
                           int((distance_to(predicted)[truth] <= tolerance_px).sum()), int(truth.sum()))
