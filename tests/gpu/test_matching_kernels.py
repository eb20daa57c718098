"""Brute-force and NCC matching against exhaustive references, with and without constraint masks."""

from __future__ import annotations

import numpy as np
import pytest

from gpu_kernels.bf_match import block_rows, match_descriptors
from gpu_kernels.harris import harris_corners
from gpu_kernels.masks import angle_window, same_value, shift_window
from gpu_kernels.ncc import match_ncc, window_descriptors
from tests.gpu.conftest import host
from tests.gpu.kernel_cases import textured_image


def naive_matches(
    a: np.ndarray, b: np.ndarray, ratio: float, mutual: bool, allowed: np.ndarray | None
) -> set[tuple[int, int]]:
    d = ((a[:, None, :].astype(np.float64) - b[None, :, :]) ** 2).sum(axis=2)
    if allowed is not None:
        d[~allowed] = np.inf
    pairs = set()
    for i in range(len(a)):
        order = np.argsort(d[i], kind="stable")
        first = d[i, order[0]]
        second = d[i, order[1]] if len(order) > 1 else np.inf
        if not np.isfinite(first) or not first < ratio * ratio * second:
            continue
        if mutual and np.argmin(d[:, order[0]]) != i:
            continue
        pairs.add((i, int(order[0])))
    return pairs


def descriptor_sets(seed: int = 0, n_a: int = 300, n_b: int = 350, dim: int = 128):
    rng = np.random.default_rng(seed)
    b = rng.random((n_b, dim)).astype(np.float32)
    a = np.vstack([b[:200] + rng.normal(0, 0.05, (200, dim)), rng.random((n_a - 200, dim))]).astype(np.float32)
    return a, b


@pytest.mark.parametrize("mutual", [True, False])
@pytest.mark.parametrize("dim", [128, 32])
def test_matcher_equals_the_naive_reference(xp, mutual: bool, dim: int) -> None:
    a, b = descriptor_sets(dim=dim)
    found = match_descriptors(xp.asarray(a), xp.asarray(b), ratio=0.8, mutual=mutual)
    pairs = set(zip(host(found.index_a).tolist(), host(found.index_b).tolist(), strict=True))
    assert pairs == naive_matches(a, b, 0.8, mutual, None) and len(pairs) >= 150
    expected = np.linalg.norm(a[host(found.index_a)] - b[host(found.index_b)], axis=1)
    assert np.allclose(host(found.distance), expected, atol=1e-3)


def test_matcher_with_constraint_masks_equals_the_naive_reference(xp) -> None:
    rng = np.random.default_rng(1)
    a, b = descriptor_sets(seed=1)
    octave_a, octave_b = rng.integers(0, 3, len(a)), rng.integers(0, 3, len(b))
    octave_a[:200] = octave_b[:200]
    xy_b = rng.uniform(0, 500, (len(b), 2))
    xy_a = np.vstack([xy_b[:200] - (30.0, -12.0) + rng.normal(0, 2, (200, 2)), rng.uniform(0, 500, (100, 2))])
    angle_a, angle_b = rng.uniform(0, 360, len(a)), rng.uniform(0, 360, len(b))
    allowed = same_value(octave_a, octave_b) & shift_window(xy_a, xy_b, (30.0, -12.0), 40.0)
    d_oct_a, d_oct_b, d_xy_a, d_xy_b = map(xp.asarray, (octave_a, octave_b, xy_a, xy_b))

    def mask(rows: slice):
        return same_value(d_oct_a[rows], d_oct_b) & shift_window(d_xy_a[rows], d_xy_b, (30.0, -12.0), 40.0)

    for budget in (2**30, 4000):  # one block, then blocks of a few rows
        found = match_descriptors(xp.asarray(a), xp.asarray(b), ratio=0.8, allowed=mask, memory_budget=budget)
        pairs = set(zip(host(found.index_a).tolist(), host(found.index_b).tolist(), strict=True))
        assert pairs == naive_matches(a, b, 0.8, True, allowed)
    assert block_rows(len(b), 4000) == 1
    within = host(angle_window(xp.asarray(angle_a), xp.asarray(angle_b), 20.0))
    assert within.mean() == pytest.approx(40 / 360, abs=0.02)  # +-20 degrees of 360


def test_blocks_do_not_change_the_result(xp) -> None:
    a, b = descriptor_sets(seed=2)
    whole = match_descriptors(xp.asarray(a), xp.asarray(b))
    blocked = match_descriptors(xp.asarray(a), xp.asarray(b), memory_budget=9 * len(b) * 7)  # 7 rows a block
    assert np.array_equal(host(whole.index_a), host(blocked.index_a))
    assert np.array_equal(host(whole.index_b), host(blocked.index_b))


def test_empty_inputs(xp) -> None:
    found = match_descriptors(xp.zeros((0, 128), xp.float32), xp.ones((5, 128), xp.float32))
    assert len(found.index_a) == 0


def naive_ncc(
    image_a: np.ndarray,
    xy_a: np.ndarray,
    image_b: np.ndarray,
    xy_b: np.ndarray,
    half: int,
    threshold: float,
    allowed: np.ndarray,
) -> set[tuple[int, int]]:
    def window(img, x, y):
        return img[y - half : y + half + 1, x - half : x + half + 1].astype(np.float64).ravel()

    scores = np.full((len(xy_a), len(xy_b)), -np.inf)
    for i, (xa, ya) in enumerate(xy_a):
        for j, (xb, yb) in enumerate(xy_b):
            if allowed[i, j]:
                scores[i, j] = np.corrcoef(window(image_a, xa, ya), window(image_b, xb, yb))[0, 1]
    pairs = set()
    for i in range(len(xy_a)):
        j = int(np.argmax(scores[i]))
        if scores[i, j] > threshold and int(np.argmax(scores[:, j])) == i:
            pairs.add((i, j))
    return pairs


def test_ncc_matching_equals_an_exhaustive_reference_and_finds_a_planted_shift(xp) -> None:
    base = textured_image(220, 260, seed=5)
    shift = (17, -9)  # image b = image a moved right 17 px and up 9 px
    image_b = np.roll(np.roll(base, shift[0], axis=1), shift[1], axis=0)

    def corners(img: np.ndarray) -> np.ndarray:
        found = harris_corners(xp.asarray(img), radius=4, threshold=1e-3, cell_px=40, per_cell=4)
        return host(found.xy).astype(int)

    corners_a, corners_b = corners(base), corners(image_b)
    desc_a, kept_a = window_descriptors(xp.asarray(base), xp.asarray(corners_a), half=7)
    desc_b, kept_b = window_descriptors(xp.asarray(image_b), xp.asarray(corners_b), half=7)
    xy_a, xy_b = corners_a[host(kept_a)], corners_b[host(kept_b)]
    allowed = shift_window(xy_a.astype(float), xy_b.astype(float), (17.0, -9.0), 25.0)
    found = match_ncc(desc_a, desc_b, threshold=0.9, allowed=xp.asarray(allowed))
    pairs = set(zip(host(found.index_a).tolist(), host(found.index_b).tolist(), strict=True))
    assert pairs == naive_ncc(base, xy_a, image_b, xy_b, 7, 0.9, allowed)
    moved = xy_b[[j for _, j in pairs]] - xy_a[[i for i, _ in pairs]]
    assert len(pairs) >= 20 and np.all(moved == np.array(shift))
    assert np.all(host(found.score) > 0.9)
