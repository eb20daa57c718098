"""The crack detector's trained classifiers and their NumPy forward passes: two per-pixel MLPs (auto-context,
Tu & Bai, PAMI 2010) and a small three-resolution U-Net (:class:`CrackNet`), with their weights
``crack_model.npz`` (trained by ``scripts/train_crack_model.py``)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

MODEL_FILE = Path(__file__).with_name("crack_model.npz")
FEATURE_VERSION = 3  # bump when pixel_features or the network change: old weights then refuse to load
# The network's convolutions in the order they run: (name, kernel size, dilation). Their widths are read
# off the weights. See :meth:`CrackNet.logits` for how they are wired.
NET_LAYERS = (
    ("enc0", 1, 1),
    ("enc1", 3, 1),
    ("half0", 3, 1),
    ("half1", 3, 2),
    ("quarter0", 3, 1),
    ("quarter1", 3, 2),
    ("quarter2", 3, 4),
    ("up_half", 3, 1),
    ("up_full", 3, 1),
    ("head", 1, 1),
)
_DILATION = {name: dilation for name, _, dilation in NET_LAYERS}


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
        x = features.reshape(-1, features.shape[-1]) - self.mean
        x /= self.scale  # in place: the same arithmetic as ``(f - mean) / scale``, one temporary fewer
        hidden = x @ self.w1
        hidden += self.b1
        np.maximum(hidden, 0.0, out=hidden)
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
    tap = np.empty((len(rows), cout), np.float32)  # one buffer for every tap: no fresh pages to fault in
    window = tap.reshape(padded.shape[0], padded.shape[1], cout)
    for i in range(k):
        for j in range(k):
            # each tap's product over the whole padded image, then its shifted window: the copies are of
            # Cout channels, not Cin
            np.matmul(rows, weight[i, j], out=tap)
            out += window[i * dilation : i * dilation + h, j * dilation : j * dilation + w]
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
        before = np.take(x, np.r_[0, 0 : n - 1], axis=axis)
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
        standard = features - self.mean
        standard /= self.scale  # in place, as ``(features - mean) / scale``
        full = self._conv("enc1", self._conv("enc0", standard))
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
        out: dict[str, np.ndarray] = {
            "feature_version": np.array(FEATURE_VERSION),
            "net_mean": self.net.mean.astype(np.float32),
            "net_scale": self.net.scale.astype(np.float32),
        }
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
            raise ValueError(
                f"crack model has feature version {int(arrays['feature_version'])}, "
                f"code expects {FEATURE_VERSION}: retrain with scripts/train_crack_model.py"
            )

        def f32(key: str) -> np.ndarray:
            return np.asarray(arrays[key], dtype=np.float32)

        stages = [
            PixelMLP(*(f32(f"{name}_{field}") for field in ("mean", "scale", "w1", "b1", "w2", "b2")))
            for name in ("stage1", "stage2")
        ]
        layers = {name: (f32(f"net_{name}_weight"), f32(f"net_{name}_bias")) for name, _, _ in NET_LAYERS}
        net = CrackNet(f32("net_mean"), f32("net_scale"), layers)
        return cls(
            stages[0], stages[1], net, float(arrays["low"]), float(arrays["high"]), float(arrays["min_length_px"])
        )


@lru_cache(maxsize=4)
def load_crack_model(path: Path = MODEL_FILE) -> CrackModel:
    """The trained model stored at ``path`` (an ``.npz`` written from :meth:`CrackModel.to_arrays`)."""
    with np.load(path, allow_pickle=False) as data:
        return CrackModel.from_arrays(dict(data))
