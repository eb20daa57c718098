"""Epipole RANSAC on planted translations with planted outliers."""

from __future__ import annotations

import numpy as np
import pytest

from gpu_kernels.epipole import ransac_epipole
from tests.gpu.conftest import host


def planted(epipole: np.ndarray, seed: int, n: int = 400, outliers: float = 0.3, noise: float = 0.3):
    """Matches of a camera translating towards homogeneous ``epipole``: each point slides along its line
    to the epipole (by how much depends on its unknown depth)."""
    rng = np.random.default_rng(seed)
    p1 = rng.uniform(0, 1000, (n, 2))
    if epipole[2] != 0:  # forward motion: points expand away from the focus of expansion
        e = epipole[:2] / epipole[2]
        p2 = e + (p1 - e) * rng.uniform(1.02, 1.3, (n, 1))
    else:  # sideways motion: every point moves along the same direction, by a depth-dependent amount
        p2 = p1 + epipole[:2] / np.linalg.norm(epipole[:2]) * rng.uniform(5, 60, (n, 1))
    p2 += rng.normal(0, noise, p2.shape)
    bad = rng.choice(n, int(outliers * n), replace=False)
    p2[bad] = rng.uniform(0, 1000, (len(bad), 2))
    truth = np.ones(n, bool)
    truth[bad] = False
    return p1, p2, truth


@pytest.mark.parametrize("epipole", [np.array([620.0, 410.0, 1.0]), np.array([1.0, 0.35, 0.0])])
def test_recovers_a_planted_epipole_among_outliers(xp, epipole: np.ndarray) -> None:
    p1, p2, truth = planted(epipole, seed=3)
    found = ransac_epipole(xp.asarray(p1), xp.asarray(p2), threshold_px=1.5, hypotheses=300)
    e, inliers = host(found.e), host(found.inliers)
    assert (inliers == truth).mean() > 0.97
    if epipole[2] != 0:
        assert np.linalg.norm(e[:2] / e[2] - epipole[:2]) < 5.0  # px, from points 0-1000 px away
    else:
        assert abs(e[2]) < 1e-3
        cos = abs(e[:2] @ epipole[:2]) / np.linalg.norm(e[:2]) / np.linalg.norm(epipole[:2])
        assert cos > np.cos(np.radians(0.5))


def test_same_result_for_the_same_seed(xp) -> None:
    p1, p2, _ = planted(np.array([300.0, 700.0, 1.0]), seed=4)
    a = ransac_epipole(xp.asarray(p1), xp.asarray(p2), seed=7)
    b = ransac_epipole(xp.asarray(p1), xp.asarray(p2), seed=7)
    assert np.array_equal(host(a.e), host(b.e)) and np.array_equal(host(a.inliers), host(b.inliers))


def test_too_few_matches(xp) -> None:
    found = ransac_epipole(xp.zeros((1, 2)), xp.zeros((1, 2)))
    assert host(found.inliers).sum() == 0
