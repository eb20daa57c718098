"""Train the two-stage crack classifier of ``workers/algorithms/cracks.py`` on CrackForest 001-040.

    .venv/bin/python scripts/train_crack_model.py [--data ../shared/data/crack_cfd] [--holdout]

Deterministic (seeded NumPy, no threads-dependent reductions beyond BLAS). Only the training split
(images 001-040) is used to fit weights and to choose the post-processing thresholds:

1. stage 1 (filter bank -> MLP) is fitted in 4 folds; its out-of-fold maps feed stage 2's context channels,
   so stage 2 learns from stage-1 maps as noisy as those it will see on new images (Tu & Bai 2010);
2. the thresholds (hysteresis low/high, minimum component extent) maximise the 2-px-tolerant F1 of a nested
   cross-validation (each outer fold's stage 2 is trained on inner out-of-fold maps of the other 30 images);
3. the final stage 1 and stage 2 are fitted on all 40 images and written as ``crack_model.npz``.

``--holdout`` then reports (does not tune on) precision/recall/F1 on images 041-060.
"""

from __future__ import annotations

import argparse
import sys
import time
from itertools import product
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from workers.algorithms.cracks import (  # noqa: E402
    MODEL_FILE,
    CrackModel,
    PixelMLP,
    ToleranceCounts,
    context_features,
    hysteresis_threshold,
    pixel_features,
    remove_short_components,
    tolerance_counts,
)

TRAIN_IDS = tuple(range(1, 41))
HOLDOUT_IDS = tuple(range(41, 61))
N_FOLDS = 4
NEGATIVES_PER_POSITIVE = 4
HIDDEN = 32
EPOCHS = 30
LOW_GRID = (0.5, 0.6, 0.7, 0.8, 0.9)
HIGH_GRID = (0.8, 0.9, 0.95)
# Capped at 40 px: CrackForest's truth holds only long cracks, so longer minima score higher there, but they
# would drop the short first cracks of a coating (and short wide cracks, whose tips fade in the map).
MIN_LENGTH_GRID = (20.0, 30.0, 40.0)


def load_pair(data: Path, index: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) BGR uint8 image and (H, W) bool crack mask of CrackForest image ``index``."""
    image = cv2.imread(str(data / "image" / f"{index:03d}.jpg"), cv2.IMREAD_COLOR)
    mask = cv2.imread(str(data / "mask_png" / f"{index:03d}.png"), cv2.IMREAD_GRAYSCALE)
    if image is None or mask is None:
        raise FileNotFoundError(f"CrackForest image or mask {index:03d} missing under {data}")
    return image, mask > 0


def sample_pixels(features: dict[int, np.ndarray], masks: dict[int, np.ndarray], ids: list[int],
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
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
    params = {"w1": rng.standard_normal((f, HIDDEN)).astype(np.float32) * np.float32(np.sqrt(2 / f)),
              "b1": np.zeros(HIDDEN, np.float32),
              "w2": rng.standard_normal(HIDDEN).astype(np.float32) * np.float32(np.sqrt(1 / HIDDEN)),
              "b2": np.zeros((), np.float32)}
    moment1 = {k: np.zeros_like(v) for k, v in params.items()}
    moment2 = {k: np.zeros_like(v) for k, v in params.items()}
    step = 0
    for _ in range(EPOCHS):
        order = rng.permutation(len(x))
        for start in range(0, len(x), batch):
            rows = order[start:start + batch]
            step += 1
            for k, g in _gradients(params, xn[rows], y[rows]).items():
                moment1[k] = 0.9 * moment1[k] + 0.1 * g
                moment2[k] = 0.999 * moment2[k] + 0.001 * g * g
                update = (moment1[k] / (1 - 0.9**step)) / (np.sqrt(moment2[k] / (1 - 0.999**step)) + 1e-8)
                params[k] = (params[k] - lr * update).astype(np.float32)
    return PixelMLP(mean.astype(np.float32), scale.astype(np.float32), params["w1"], params["b1"], params["w2"],
                    params["b2"])


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


def out_of_fold_inputs(base: dict[int, np.ndarray], masks: dict[int, np.ndarray], ids: list[int], n_folds: int,
                       seed: int) -> dict[int, np.ndarray]:
    """Stage-2 inputs of every image of ``ids``, its context from a stage 1 that did not see it."""
    out = {}
    for k in range(n_folds):
        held = ids[k::n_folds]
        stage1 = fit_stage(base, masks, [i for i in ids if i not in held], seed + k)
        out.update({i: with_context(base[i], stage1) for i in held})
    return out


def fit_model(base: dict[int, np.ndarray], masks: dict[int, np.ndarray], ids: list[int], n_folds: int, seed: int,
              thresholds: tuple[float, float, float] = (0.5, 0.5, 0.0)) -> CrackModel:
    """Both stages on ``ids``: stage 2 on out-of-fold stage-1 context, stage 1 on all of ``ids``."""
    stage2 = fit_stage(out_of_fold_inputs(base, masks, ids, n_folds, seed), masks, ids, seed + 100)
    return CrackModel(fit_stage(base, masks, ids, seed + 200), stage2, *thresholds)


def nested_cv_probabilities(base: dict[int, np.ndarray], masks: dict[int, np.ndarray], ids: list[int],
                            seed: int) -> dict[int, np.ndarray]:
    """(H, W) stage-2 probability of every image of ``ids`` from a model fitted without it."""
    out = {}
    for k in range(N_FOLDS):
        held = ids[k::N_FOLDS]
        model = fit_model(base, masks, [i for i in ids if i not in held], N_FOLDS - 1, seed + 1000 * (k + 1))
        out.update({i: model.stage2.predict(with_context(base[i], model.stage1)) for i in held})
    return out


def post_process(probability: np.ndarray, low: float, high: float, min_length_px: float) -> np.ndarray:
    return remove_short_components(hysteresis_threshold(probability, low, high), min_length_px)


def choose_thresholds(probabilities: dict[int, np.ndarray], masks: dict[int, np.ndarray]
                      ) -> tuple[tuple[float, float, float], ToleranceCounts]:
    """The (low, high, min_length_px) of the grid with the best pooled 2-px F1, and its counts."""
    best: tuple[tuple[float, float, float], ToleranceCounts] | None = None
    for low, high, min_length in product(LOW_GRID, HIGH_GRID, MIN_LENGTH_GRID):
        if low > high:
            continue
        counts = sum((tolerance_counts(post_process(p, low, high, min_length), masks[i])
                      for i, p in probabilities.items()), ToleranceCounts(0, 0, 0, 0))
        if best is None or counts.f1 > best[1].f1:
            best = ((low, high, min_length), counts)
    assert best is not None
    return best


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "crack_cfd")
    parser.add_argument("--out", type=Path, default=MODEL_FILE)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--holdout", action="store_true", help="report (never tune on) images 041-060")
    args = parser.parse_args()
    ids = list(TRAIN_IDS)
    pairs = {i: load_pair(args.data, i) for i in ids}
    base = {i: pixel_features(image) for i, (image, _) in pairs.items()}
    masks = {i: mask for i, (_, mask) in pairs.items()}
    thresholds, cv_counts = choose_thresholds(nested_cv_probabilities(base, masks, ids, args.seed), masks)
    print(f"thresholds low/high/min_length_px {thresholds}; " + describe("nested CV on 001-040", cv_counts))
    model = fit_model(base, masks, ids, N_FOLDS, args.seed, thresholds)
    np.savez(args.out, **cast(dict[str, Any], model.to_arrays()))  # numpy's stub types **kwds as bool
    print(f"wrote {args.out}")
    counts, seconds = evaluate(model, args.data, TRAIN_IDS)
    print(describe("training images 001-040 (resubstitution)", counts) + f"; {seconds * 1000:.0f} ms/image")
    if args.holdout:
        print(describe("held-out images 041-060", evaluate(model, args.data, HOLDOUT_IDS)[0]))


if __name__ == "__main__":
    main()
