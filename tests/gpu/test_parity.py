"""CuPy against NumPy: every kernel gives the same result on both, within float32 tolerance."""

from __future__ import annotations

import numpy as np
import pytest

from gpu_kernels.backend import cuda_available
from gpu_kernels.bf_match import match_descriptors
from gpu_kernels.epipole import ransac_epipole
from gpu_kernels.harris import harris_corners, harris_response
from gpu_kernels.ncc import window_descriptors
from gpu_kernels.sift import sift
from tests.gpu.conftest import host
from tests.gpu.kernel_cases import textured_image

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not cuda_available(), reason="needs CuPy and a CUDA device")]


@pytest.fixture(scope="module")
def cp():
    import cupy

    return cupy


def test_harris_parity(cp) -> None:
    img = textured_image(400, 600, seed=1)
    assert np.allclose(host(harris_response(cp.asarray(img))), harris_response(img), rtol=1e-4, atol=1e-7)
    a, b = harris_corners(img), harris_corners(cp.asarray(img))
    assert np.array_equal(a.xy, host(b.xy))


def test_matching_and_ncc_parity(cp) -> None:
    rng = np.random.default_rng(0)
    d1, d2 = rng.random((2000, 128), dtype=np.float32), rng.random((2500, 128), dtype=np.float32)
    a, b = match_descriptors(d1, d2), match_descriptors(cp.asarray(d1), cp.asarray(d2))
    assert np.array_equal(a.index_a, host(b.index_a)) and np.array_equal(a.index_b, host(b.index_b))
    img = textured_image(200, 200, seed=2)
    xy = rng.integers(10, 190, (300, 2))
    na, _ = window_descriptors(img, xy, 7)
    ca, _ = window_descriptors(cp.asarray(img), cp.asarray(xy), 7)
    assert np.allclose(na, host(ca), atol=1e-5)


def test_sift_parity(cp) -> None:
    img = textured_image(300, 400, seed=3)
    a, b = sift(img), sift(cp.asarray(img))
    assert abs(len(a.xy) - len(b.xy)) <= 0.01 * len(a.xy)  # float32 summation order may flip a borderline point
    near = np.linalg.norm(a.xy[:, None, :] - host(b.xy)[None], axis=2).min(axis=1)
    assert (near < 1e-3).mean() > 0.99


def test_epipole_parity(cp) -> None:
    rng = np.random.default_rng(4)
    p1 = rng.uniform(0, 1000, (300, 2))
    p2 = p1 + np.array([1.0, 0.3]) * rng.uniform(5, 50, (300, 1))
    a, b = ransac_epipole(p1, p2), ransac_epipole(cp.asarray(p1), cp.asarray(p2))
    assert np.allclose(np.abs(a.e), np.abs(host(b.e)), atol=1e-6)
    assert np.array_equal(a.inliers, host(b.inliers))
