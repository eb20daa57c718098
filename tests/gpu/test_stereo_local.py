"""The local stereo matcher against the formula evaluated pixel by pixel, on NumPy and CuPy."""

from __future__ import annotations

import cv2
import numpy as np

from gpu_kernels.stereo_local import epipolar_terms, match_local, window_weights
from tests.gpu.conftest import host


def textured_pair(seed: int, h: int = 40, w: int = 64, d: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    left = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32) * 255, (0, 0), 1.2)
    shift = np.float32([[1, 0, -d], [0, 1, 0]])  # right(x) = left(x + d)
    right = cv2.warpAffine(left, shift, (w, h), borderMode=cv2.BORDER_REFLECT) + rng.normal(0, 2, (h, w))
    return left, right.astype(np.float32)


def naive_energies(left, right, f, u0, v0, disparities, vr, r, lam):
    """E(d, dv) of the pixel (u0, v0), straight from the sum over its window (interior pixels only)."""
    k = window_weights(r).astype(np.float64)
    lines = np.asarray(f, dtype=np.float64)
    energies = {}
    for dv in range(-vr, vr + 1):
        for d in disparities:
            e = 0.0
            for j in range(-r, r + 1):
                for i in range(-r, r + 1):
                    u, v = u0 + i, v0 + j
                    line = lines @ np.array([u, v, 1.0])
                    dist = (line @ np.array([u - d, v + dv, 1.0])) / np.hypot(line[0], line[1])
                    diff = abs(float(left[v, u]) - float(right[v + dv, u - d]))
                    e += k[i + r] * k[j + r] * (1.0 + lam * dist * dist) * diff
            energies[(d, dv)] = e
    return energies


def test_matches_the_formula_pixel_by_pixel(xp) -> None:
    left, right = textured_pair(seed=1)
    f = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, -0.3]]) + 1e-4 * np.eye(3)
    m = match_local(
        xp.asarray(left), xp.asarray(right), 12, vertical_radius=1, fundamental=f, epipolar_weight=0.5, window_radius=2
    )
    disp, vert, cost = host(m.disparity), host(m.vertical), host(m.cost)
    for u0, v0 in [(20, 10), (33, 17), (45, 25), (58, 30), (16, 35)]:
        energies = naive_energies(left, right, f, u0, v0, range(12), 1, 2, 0.5)
        (d, dv), e = min(energies.items(), key=lambda kv: kv[1])
        assert abs(disp[v0, u0] - d) <= 0.5
        assert vert[v0, u0] == dv
        assert np.isclose(cost[v0, u0], e, rtol=1e-4)


def test_epipolar_terms_give_distances(xp) -> None:
    f = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, -2.0]])  # right lines y = v - 2
    base, a, b = (host(t) for t in epipolar_terms(f, (5, 6), xp))
    # (u, v) is 2 px above its line (sign as F gives it); a candidate 2 rows up lies on it
    assert np.allclose(np.abs(base), 2.0)
    assert np.allclose(base + b * -2.0, 0.0)
    assert np.allclose(a, 0.0)


def test_cupy_equals_numpy(xp) -> None:
    left, right = textured_pair(seed=2, h=48, w=80)
    ours = match_local(xp.asarray(left), xp.asarray(right), 16, window_radius=3, truncate=40.0)
    twin = match_local(left, right, 16, window_radius=3, truncate=40.0)
    for name in ("disparity", "vertical", "right_disparity"):
        a, b = host(getattr(ours, name)), getattr(twin, name)
        same = (np.isnan(a) & np.isnan(b)) | (np.abs(a - b) <= 1e-3)
        assert same.mean() >= 0.999, name
    assert np.allclose(host(ours.cost), twin.cost, rtol=1e-4, atol=1e-4)
