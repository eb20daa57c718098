"""Harris corners against cv2.cornerHarris and naive references."""

from __future__ import annotations

import cv2
import numpy as np

from gpu_kernels.harris import cap_per_cell, compact, harris_corners, harris_response, suppress_non_maxima
from tests.gpu.conftest import host
from tests.gpu.kernel_cases import textured_image


def test_response_equals_opencv_with_the_same_kernels(xp) -> None:
    img = textured_image(240, 320, seed=1)
    ours = host(harris_response(xp.asarray(img), k=0.04, window="box", scale=1.0 / (4 * 3 * 255)))
    reference = cv2.cornerHarris(img, blockSize=3, ksize=3, k=0.04)
    assert np.abs(ours - reference).max() <= 1e-4 * np.abs(reference).max()


def test_suppression_and_compaction_match_a_naive_reference(xp) -> None:
    rng = np.random.default_rng(2)
    response = rng.random((40, 50)).astype(np.float32)
    mask = host(suppress_non_maxima(xp.asarray(response), radius=2, threshold=0.5))
    naive = np.zeros_like(mask)
    for y in range(40):
        for x in range(50):
            window = response[max(y - 2, 0) : y + 3, max(x - 2, 0) : x + 3]
            naive[y, x] = response[y, x] > 0.5 and response[y, x] == window.max()
    assert np.array_equal(mask, naive)
    corners = compact(xp.asarray(mask), xp.asarray(response))
    ys, xs = np.nonzero(naive)
    order = np.argsort(-response[ys, xs], kind="stable")
    assert np.array_equal(host(corners.xy), np.column_stack([xs[order], ys[order]]).astype(np.float32))
    assert np.all(np.diff(host(corners.response)) <= 0)


def test_tiled_detection_equals_untiled(xp) -> None:
    img = xp.asarray(textured_image(300, 500, seed=3))
    whole = harris_corners(img, radius=3, threshold=1e-4)
    tiled = harris_corners(img, radius=3, threshold=1e-4, tile=64)
    assert len(whole.xy) > 200
    assert np.array_equal(host(whole.xy), host(tiled.xy))
    assert np.array_equal(host(whole.response), host(tiled.response))


def test_cap_per_cell_keeps_the_strongest_of_each_cell(xp) -> None:
    img = textured_image(256, 256, seed=4)
    corners = harris_corners(xp.asarray(img), radius=2, threshold=1e-5)
    capped = cap_per_cell(corners, img.shape, cell_px=64, per_cell=5)
    xy, resp = host(corners.xy), host(corners.response)
    cxy, cresp = host(capped.xy), host(capped.response)
    cells = (cxy[:, 1] // 64) * 4 + cxy[:, 0] // 64
    assert np.bincount(cells.astype(int)).max() <= 5 and np.all(np.diff(cresp) <= 0)
    all_cells = (xy[:, 1] // 64) * 4 + xy[:, 0] // 64
    for cell in range(16):
        want = np.sort(resp[all_cells == cell])[::-1][:5]
        assert np.array_equal(np.sort(cresp[cells == cell])[::-1], want)


def test_corners_of_a_planted_square_are_found(xp) -> None:
    img = np.zeros((100, 100), np.uint8)
    img[30:70, 30:70] = 200
    corners = host(harris_corners(xp.asarray(img), radius=5, threshold=1e-3).xy)
    planted = np.array([[29.5, 29.5], [69.5, 29.5], [29.5, 69.5], [69.5, 69.5]])
    distances = np.linalg.norm(corners[:, None, :] - planted[None], axis=2)
    assert len(corners) == 4 and distances.min(axis=0).max() <= 1.5
