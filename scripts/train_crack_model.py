"""Train the crack classifiers of ``workers/algorithms/cracks.py`` on CrackForest images 001-040.

    python -m venv /tmp/trainenv && /tmp/trainenv/bin/pip install torch numpy scipy opencv-python-headless
    OMP_NUM_THREADS=1 /tmp/trainenv/bin/python scripts/train_crack_model.py [--data ../shared/data/crack_cfd]

Training needs PyTorch (the CPU build; 22 min on one core of the 2-core dev machine, ~8 GB of memory). The
service does not: its inference is NumPy/OpenCV, and a unit test checks the NumPy forward pass against
:class:`TorchCrackNet`. Deterministic (seeded NumPy and torch, one thread, deterministic kernels): two runs
wrote identical weights. Only the training split, images 001-040, fits weights and chooses anything:

1. the features of every image (:func:`~workers.algorithms.cracks.detection.pixel_features`) and of its
   ``AUGMENTATIONS`` are computed once;
2. the auto-context MLPs are fitted in NumPy on the full-resolution filter bank: stage 1 in inner folds,
   whose out-of-fold maps feed stage 2's context channels (Tu & Bai 2010), then stage 1 on all images;
3. the U-Net trains (Adam, 1200 steps) on random 128 px crops of the images and their augmented copies (half
   the crops centred on a crack pixel), each under one of the 8 flips and quarter-turns (the features are
   equivariant to them), with a class-weighted cross-entropy;
4. 4-fold cross-validation, the folds runs of consecutive images (:func:`folds`; interleaved folds put
   photos of the same stretch of road on both sides), gives every image a probability map (the mean of
   both classifiers) from a model that did not see it; the hysteresis thresholds and the minimum component
   extent maximise the pooled 2-px-tolerant F1 of these maps. Also printed: the F1 when each fold is scored
   at thresholds chosen on the other three folds only (nested);
5. the final model is fitted on all 40 images and written, with those thresholds, as ``crack_model.npz``.

The design (features, network widths, steps, loss weights, augmentation, averaging with the MLPs) was chosen
by this cross-validation over several seeds, on clean folds and on folds under exposure, contrast, scale,
blur, JPEG and noise changes. ``--holdout`` reports (never tunes on) precision/recall/F1 on images 041-060.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from itertools import product
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from workers.algorithms.cracks import (  # noqa: E402
    MODEL_FILE,
    N_BANK,
    NET_LAYERS,
    CrackModel,
    CrackNet,
    PixelMLP,
    ToleranceCounts,
    context_features,
    features_probability,
    hysteresis_threshold,
    pixel_features,
    remove_short_components,
    tolerance_counts,
)

try:
    import torch
    from torch import nn
    from torch.nn import functional as F
except ImportError as exc:  # the service does not need torch; only this script does
    raise SystemExit("training needs PyTorch: see the first lines of scripts/train_crack_model.py") from exc

TRAIN_IDS = tuple(range(1, 41))
HOLDOUT_IDS = tuple(range(41, 61))
N_FOLDS = 4
# The network also trains on these copies of each training image (resampled by a factor, or blurred by a
# Gaussian of sigma px): without them its precision collapsed on cross-validation folds seen 1.33x larger
# or blurred (cracks wider and softer than any it was trained on), where the MLPs held up.
AUGMENTATIONS = (("scale", 0.8), ("scale", 1.25), ("blur", 1.0))
# the auto-context MLPs (NumPy)
NEGATIVES_PER_POSITIVE = 4
HIDDEN = 32
EPOCHS = 30
LOW_GRID = (0.3, 0.4, 0.5, 0.6, 0.7, 0.8)
HIGH_GRID = (0.5, 0.6, 0.7, 0.8, 0.9)
# Capped at 40 px: CrackForest's truth holds only long cracks, so longer minima score higher there, but they
# would drop the short first cracks of a coating (and short wide cracks, whose tips fade in the map).
MIN_LENGTH_GRID = (20.0, 30.0, 40.0)


Thresholds = tuple[float, float, float]
Key = int | tuple[int, str]  # an image number, or an image number and the name of an augmented copy


@dataclass(frozen=True)
class TrainConfig:
    """Network widths and optimisation settings (chosen by cross-validation on 001-040)."""

    widths: tuple[int, int, int] = (12, 16, 8)  # channels at full, half/quarter, and the last full-res layer
    steps: int = 1200
    batch: int = 8
    crop: int = 128  # px, a multiple of 4
    lr: float = 3e-3  # Adam, cosine decay to zero
    pos_weight: float = 3.0  # loss weight of a crack pixel relative to a background pixel
    ignore_px: float = 0.0  # background pixels this close to a labelled crack pixel carry no loss
    crack_centred: float = 0.5  # fraction of crops centred on a crack pixel
    weight_decay: float = 0.0


def augmented(image: np.ndarray, mask: np.ndarray, kind: str, value: float) -> tuple[np.ndarray, np.ndarray]:
    """A training copy of ``image`` (H, W, 3) uint8 and ``mask`` (H, W) bool: see ``AUGMENTATIONS``."""
    if kind == "blur":
        return cv2.GaussianBlur(image, (0, 0), value), mask
    if kind != "scale":
        raise ValueError(f"unknown augmentation {kind}")
    h, w = mask.shape
    size = (int(round(w * value / 4)) * 4, int(round(h * value / 4)) * 4)  # crops need multiples of 4
    resized = cv2.resize(image, size, interpolation=cv2.INTER_AREA if value < 1 else cv2.INTER_LINEAR)
    return resized, cv2.resize(mask.astype(np.float32), size, interpolation=cv2.INTER_LINEAR) >= 0.5


def sample_pixels(
    features: dict[int, np.ndarray], masks: dict[int, np.ndarray], ids: list[int], rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """All crack pixels of ``ids`` and ``NEGATIVES_PER_POSITIVE`` times as many random background pixels."""
    xs, ys = [], []
    for i in ids:
        flat, labels = features[i].reshape(-1, features[i].shape[-1]), masks[i].ravel()
        pos, neg = np.flatnonzero(labels), np.flatnonzero(~labels)
        neg = rng.choice(neg, min(len(neg), NEGATIVES_PER_POSITIVE * len(pos)), replace=False)
        xs.append(flat[np.concatenate([pos, neg])])
        ys.append(np.r_[np.ones(len(pos)), np.zeros(len(neg))])
    return np.concatenate(xs).astype(np.float32), np.concatenate(ys).astype(np.float32)


def fit_mlp(x: np.ndarray, y: np.ndarray, seed: int, lr: float = 3e-3, batch: int = 1024) -> PixelMLP:
    """Fit a :class:`PixelMLP` by Adam (Kingma & Ba 2015) on the cross-entropy; ``x`` (N, F), ``y`` (N,) 0/1."""
    rng = np.random.default_rng(seed)
    mean, scale = x.mean(axis=0), x.std(axis=0) + 1e-6
    xn, f = (x - mean) / scale, x.shape[1]
    params = {
        "w1": rng.standard_normal((f, HIDDEN)).astype(np.float32) * np.float32(np.sqrt(2 / f)),
        "b1": np.zeros(HIDDEN, np.float32),
        "w2": rng.standard_normal(HIDDEN).astype(np.float32) * np.float32(np.sqrt(1 / HIDDEN)),
        "b2": np.zeros((), np.float32),
    }
    moment1 = {k: np.zeros_like(v) for k, v in params.items()}
    moment2 = {k: np.zeros_like(v) for k, v in params.items()}
    step = 0
    for _ in range(EPOCHS):
        order = rng.permutation(len(x))
        for start in range(0, len(x), batch):
            rows = order[start : start + batch]
            step += 1
            for k, g in _gradients(params, xn[rows], y[rows]).items():
                moment1[k] = 0.9 * moment1[k] + 0.1 * g
                moment2[k] = 0.999 * moment2[k] + 0.001 * g * g
                update = (moment1[k] / (1 - 0.9**step)) / (np.sqrt(moment2[k] / (1 - 0.999**step)) + 1e-8)
                params[k] = (params[k] - lr * update).astype(np.float32)
    return PixelMLP(
        mean.astype(np.float32), scale.astype(np.float32), params["w1"], params["b1"], params["w2"], params["b2"]
    )


def _gradients(params: dict[str, np.ndarray], x: np.ndarray, y: np.ndarray) -> dict[str, np.ndarray]:
    """Mean cross-entropy gradients of the one-hidden-layer MLP on a batch."""
    pre = x @ params["w1"] + params["b1"]
    hidden = np.maximum(pre, 0)
    p = 1 / (1 + np.exp(-np.clip(hidden @ params["w2"] + params["b2"], -30, 30)))
    dz = (p - y) / len(y)
    dhidden = np.outer(dz, params["w2"]) * (pre > 0)
    return {"w1": x.T @ dhidden, "b1": dhidden.sum(axis=0), "w2": hidden.T @ dz, "b2": dz.sum()}


def fit_stage(features: dict[int, np.ndarray], masks: dict[int, np.ndarray], ids: list[int], seed: int) -> PixelMLP:
    """One MLP fitted on the sampled pixels of ``ids`` (features (H, W, F) per image)."""
    x, y = sample_pixels(features, masks, ids, np.random.default_rng(seed))
    return fit_mlp(x, y, seed)


def with_context(base: np.ndarray, stage1: PixelMLP) -> np.ndarray:
    """(H, W, F + C) stage-2 input: base features and the context channels of ``stage1``'s map."""
    return np.concatenate([base, context_features(stage1.predict(base))], axis=-1)


def out_of_fold_inputs(
    base: dict[int, np.ndarray], masks: dict[int, np.ndarray], ids: list[int], n_folds: int, seed: int
) -> dict[int, np.ndarray]:
    """Stage-2 inputs of every image of ``ids``, its context from a stage 1 that did not see it."""
    out = {}
    for k in range(n_folds):
        held = ids[k::n_folds]
        stage1 = fit_stage(base, masks, [i for i in ids if i not in held], seed + k)
        out.update({i: with_context(base[i], stage1) for i in held})
    return out


def fit_auto_context(
    bank: dict[int, np.ndarray], masks: dict[int, np.ndarray], ids: list[int], n_folds: int, seed: int
) -> tuple[PixelMLP, PixelMLP]:
    """Both MLPs on ``ids``: stage 2 on out-of-fold stage-1 context, stage 1 on all of ``ids``."""
    stage2 = fit_stage(out_of_fold_inputs(bank, masks, ids, n_folds, seed), masks, ids, seed + 100)
    return fit_stage(bank, masks, ids, seed + 200), stage2


class TorchCrackNet(nn.Module):
    """The network of :class:`workers.algorithms.cracks.detection.CrackNet`, layer for layer, in PyTorch."""

    def __init__(self, n_features: int, widths: tuple[int, int, int]) -> None:
        super().__init__()
        a, b, c = widths
        shapes = {
            "enc0": (n_features, a),
            "enc1": (a, a),
            "half0": (a, b),
            "half1": (b, b),
            "quarter0": (b, b),
            "quarter1": (b, b),
            "quarter2": (b, b),
            "up_half": (2 * b, b),
            "up_full": (a + b, c),
            "head": (c, 1),
        }
        self.convs = nn.ModuleDict(
            {name: nn.Conv2d(*shapes[name], k, padding=d * (k // 2), dilation=d) for name, k, d in NET_LAYERS}
        )
        self.register_buffer("mean", torch.zeros(n_features, 1, 1))
        self.register_buffer("scale", torch.ones(n_features, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, H, W) logits of (N, F, H, W) raw features, H and W multiples of 4."""
        c = self.convs

        def up(t: torch.Tensor) -> torch.Tensor:
            return F.interpolate(t, scale_factor=2, mode="bilinear", align_corners=False)

        full = F.relu(c["enc1"](F.relu(c["enc0"]((x - self.mean) / self.scale))))
        half = F.relu(c["half1"](F.relu(c["half0"](F.avg_pool2d(full, 2)))))
        quarter = F.avg_pool2d(half, 2)
        for name in ("quarter0", "quarter1", "quarter2"):
            quarter = F.relu(c[name](quarter))
        half = F.relu(c["up_half"](torch.cat([half, up(quarter)], 1)))
        full = F.relu(c["up_full"](torch.cat([full, up(half)], 1)))
        return c["head"](full)[:, 0]

    def to_numpy(self) -> CrackNet:
        """The same network for :mod:`workers.algorithms.cracks.detection` (weights as (k, k, Cin, Cout))."""
        layers = {
            name: (
                conv.weight.detach().cpu().numpy().transpose(2, 3, 1, 0).astype(np.float32),
                conv.bias.detach().cpu().numpy().astype(np.float32),
            )
            for name, conv in self.convs.items()
        }
        return CrackNet(
            self.mean.cpu().numpy().ravel().astype(np.float32),
            self.scale.cpu().numpy().ravel().astype(np.float32),
            layers,
        )


def load_pair(data: Path, index: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) BGR uint8 image and (H, W) bool crack mask of CrackForest image ``index``."""
    image = cv2.imread(str(data / "image" / f"{index:03d}.jpg"), cv2.IMREAD_COLOR)
    mask = cv2.imread(str(data / "mask_png" / f"{index:03d}.png"), cv2.IMREAD_GRAYSCALE)
    if image is None or mask is None:
        raise FileNotFoundError(f"CrackForest image or mask {index:03d} missing under {data}")
    return image, mask > 0


def loss_weights(mask: np.ndarray, cfg: TrainConfig) -> np.ndarray:
    """(H, W) float32 per-pixel loss weight: ``pos_weight`` on cracks, 0 on background within ``ignore_px``."""
    weight = np.where(mask, np.float32(cfg.pos_weight), np.float32(1.0))
    if cfg.ignore_px > 0:
        distance = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        weight[~mask & (distance <= cfg.ignore_px)] = 0.0
    return weight.astype(np.float32)


def dihedral(t: torch.Tensor, k: int) -> torch.Tensor:
    """``t`` (..., S, S) under the ``k``-th (0-7) of the 8 flips and quarter-turns of a square."""
    t = torch.rot90(t, k % 4, dims=(-2, -1))
    return torch.flip(t, dims=(-1,)) if k >= 4 else t


def sample_batch(
    features: list[torch.Tensor],
    targets: list[torch.Tensor],
    weights: list[torch.Tensor],
    crack_pixels: list[np.ndarray],
    cfg: TrainConfig,
    rng: np.random.Generator,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``cfg.batch`` random crops: features (B, F, S, S), targets (B, S, S), weights (B, S, S)."""
    xs, ys, ws = [], [], []
    s = cfg.crop
    for _ in range(cfg.batch):
        i = int(rng.integers(len(features)))
        h, w = features[i].shape[1:]
        if rng.random() < cfg.crack_centred and len(crack_pixels[i]):
            cy, cx = crack_pixels[i][rng.integers(len(crack_pixels[i]))]
            top, left = int(np.clip(cy - s // 2, 0, h - s)), int(np.clip(cx - s // 2, 0, w - s))
        else:
            top, left = int(rng.integers(h - s + 1)), int(rng.integers(w - s + 1))
        k = int(rng.integers(8))
        window = (slice(top, top + s), slice(left, left + s))
        xs.append(dihedral(features[i][:, window[0], window[1]], k))
        ys.append(dihedral(targets[i][window], k))
        ws.append(dihedral(weights[i][window], k))
    return torch.stack(xs), torch.stack(ys), torch.stack(ws)


def feature_statistics(features: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(F,) float32 mean and standard deviation (+1e-6) over all pixels of (H, W, F) feature maps."""
    n = sum(f.shape[0] * f.shape[1] for f in features)
    total = sum(f.sum(axis=(0, 1), dtype=np.float64) for f in features)
    mean = np.asarray(total) / n
    var = sum(((f - mean) ** 2).sum(axis=(0, 1)) for f in features) / n
    return mean.astype(np.float32), (np.sqrt(np.asarray(var)) + 1e-6).astype(np.float32)


def train_net(
    features: dict[Key, np.ndarray],
    masks: dict[Key, np.ndarray],
    keys: list[Key],
    cfg: TrainConfig,
    seed: int,
    device: str = "cpu",
) -> TorchCrackNet:
    """A network fitted on the images ``keys`` (features (H, W, F) and masks (H, W) bool per image)."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    mean, scale = feature_statistics([features[k] for k in keys])
    net = TorchCrackNet(len(mean), cfg.widths)
    net.mean.copy_(torch.from_numpy(mean)[:, None, None])
    net.scale.copy_(torch.from_numpy(scale)[:, None, None])
    net = net.to(device)
    inputs = [torch.from_numpy(np.ascontiguousarray(features[k].transpose(2, 0, 1))).to(device) for k in keys]
    targets = [torch.from_numpy(masks[k].astype(np.float32)).to(device) for k in keys]
    weights = [torch.from_numpy(loss_weights(masks[k], cfg)).to(device) for k in keys]
    crack_pixels = [np.argwhere(masks[k]) for k in keys]
    optimiser = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, cfg.steps)
    for _ in range(cfg.steps):
        x, y, w = sample_batch(inputs, targets, weights, crack_pixels, cfg, rng)
        loss = (F.binary_cross_entropy_with_logits(net(x), y, reduction="none") * w).sum() / w.sum().clamp(min=1.0)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
    return net.cpu().eval()


def fit_model(
    features: dict[Key, np.ndarray],
    masks: dict[Key, np.ndarray],
    ids: list[int],
    n_folds: int,
    cfg: TrainConfig,
    seed: int,
    thresholds: Thresholds = (0.5, 0.5, 0.0),
) -> CrackModel:
    """Both classifiers on the images ``ids``: the MLPs on their filter bank (stage 2 on ``n_folds``-fold
    out-of-fold context), the network on their features and those of their augmented copies."""
    bank = {i: features[i][..., :N_BANK] for i in ids}
    stage1, stage2 = fit_auto_context(bank, {i: masks[i] for i in ids}, ids, n_folds, seed)
    keys: list[Key] = [*ids, *((i, f"{kind}{value}") for i in ids for kind, value in AUGMENTATIONS)]
    net = train_net(features, masks, keys, cfg, seed).to_numpy()
    return CrackModel(stage1, stage2, net, *thresholds)


def folds(ids: list[int]) -> list[list[int]]:
    """``N_FOLDS`` runs of consecutive image numbers: the held-out split 041-060 is such a run too, and
    neighbouring CrackForest photos often show the same stretch of road, so interleaved folds would flatter."""
    ordered = sorted(ids)
    bounds = np.linspace(0, len(ordered), N_FOLDS + 1).round().astype(int)
    return [ordered[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def cross_validated_maps(
    features: dict[Key, np.ndarray], masks: dict[Key, np.ndarray], ids: list[int], cfg: TrainConfig, seed: int
) -> dict[int, np.ndarray]:
    """Every image's probability map from a model fitted on the other folds of :func:`folds`."""
    out = {}
    for k, held in enumerate(folds(ids)):
        model = fit_model(features, masks, [i for i in ids if i not in held], N_FOLDS - 1, cfg, seed + 1000 * (k + 1))
        out.update({i: features_probability(features[i], model) for i in held})
    return out


def post_process(probability: np.ndarray, low: float, high: float, min_length_px: float) -> np.ndarray:
    return remove_short_components(hysteresis_threshold(probability, low, high), min_length_px)


def grid_counts(
    probabilities: dict[int, np.ndarray], masks: dict[int, np.ndarray]
) -> dict[Thresholds, dict[int, ToleranceCounts]]:
    """Per (low, high, min_length_px) of the grid, each image's 2-px counts."""
    out: dict[Thresholds, dict[int, ToleranceCounts]] = {}
    for low, high, min_length in product(LOW_GRID, HIGH_GRID, MIN_LENGTH_GRID):
        if low <= high:
            out[(low, high, min_length)] = {
                i: tolerance_counts(post_process(p, low, high, min_length), masks[i]) for i, p in probabilities.items()
            }
    return out


def pooled(counts: dict[int, ToleranceCounts], ids: list[int]) -> ToleranceCounts:
    return sum((counts[i] for i in ids), ToleranceCounts(0, 0, 0, 0))


def choose_thresholds(
    grid: dict[Thresholds, dict[int, ToleranceCounts]], ids: list[int]
) -> tuple[Thresholds, ToleranceCounts]:
    """The grid point with the best pooled F1 over ``ids``, and those counts."""
    best = max(grid, key=lambda t: pooled(grid[t], ids).f1)
    return best, pooled(grid[best], ids)


def nested_counts(grid: dict[Thresholds, dict[int, ToleranceCounts]], ids: list[int]) -> ToleranceCounts:
    """Pooled counts when each fold is scored at the thresholds chosen on the other folds."""
    total = ToleranceCounts(0, 0, 0, 0)
    for held in folds(ids):
        chosen, _ = choose_thresholds(grid, [i for i in ids if i not in held])
        total = total + pooled(grid[chosen], held)
    return total


def evaluate(model: CrackModel, data: Path, ids: tuple[int, ...]) -> tuple[ToleranceCounts, float]:
    """Pooled 2-px counts of ``detect_cracks`` over ``ids`` and the mean seconds per image."""
    from workers.algorithms.cracks import detect_cracks

    total, seconds = ToleranceCounts(0, 0, 0, 0), 0.0
    for i in ids:
        image, mask = load_pair(data, i)
        start = time.perf_counter()
        found = detect_cracks(image, model=model)
        seconds += time.perf_counter() - start
        total = total + tolerance_counts(found, mask)
    return total, seconds / len(ids)


def describe(name: str, counts: ToleranceCounts) -> str:
    return f"{name}: precision {counts.precision:.3f} recall {counts.recall:.3f} F1 {counts.f1:.3f}"


def load_training_set(data: Path, ids: list[int]) -> tuple[dict[Key, np.ndarray], dict[Key, np.ndarray]]:
    """Features (H, W, F) and masks (H, W) bool of the images ``ids`` and of their ``AUGMENTATIONS``."""
    features: dict[Key, np.ndarray] = {}
    masks: dict[Key, np.ndarray] = {}
    for i in ids:
        image, mask = load_pair(data, i)
        features[i], masks[i] = pixel_features(image), mask
        for kind, value in AUGMENTATIONS:
            copy, copy_mask = augmented(image, mask, kind, value)
            features[(i, f"{kind}{value}")], masks[(i, f"{kind}{value}")] = pixel_features(copy), copy_mask
    return features, masks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "crack_cfd")
    parser.add_argument("--out", type=Path, default=MODEL_FILE)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--holdout", action="store_true", help="report (never tune on) images 041-060")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True)
    started = time.perf_counter()
    cfg, ids = TrainConfig(), list(TRAIN_IDS)
    features, masks = load_training_set(args.data, ids)
    grid = grid_counts(cross_validated_maps(features, masks, ids, cfg, args.seed), {i: masks[i] for i in ids})
    thresholds, cv_counts = choose_thresholds(grid, ids)
    print(f"thresholds low/high/min_length_px {thresholds}; " + describe("4-fold CV on 001-040", cv_counts))
    print(describe("4-fold CV on 001-040, thresholds nested", nested_counts(grid, ids)))
    model = fit_model(features, masks, ids, N_FOLDS, cfg, args.seed, thresholds)
    np.savez(args.out, **cast(dict[str, Any], model.to_arrays()))  # numpy's stub types **kwds as bool
    print(f"wrote {args.out} after {time.perf_counter() - started:.0f} s")
    counts, seconds = evaluate(model, args.data, TRAIN_IDS)
    print(describe("training images 001-040 (resubstitution)", counts) + f"; {seconds * 1000:.0f} ms/image")
    if args.holdout:
        print(describe("held-out images 041-060", evaluate(model, args.data, HOLDOUT_IDS)[0]))


if __name__ == "__main__":
    main()
