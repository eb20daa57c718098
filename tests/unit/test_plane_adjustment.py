"""The vectorised planar adjustment: its dense and sparse normal equations give the same solution, and a
long GPS strip (where the sparse path is what runs) still follows its fixes."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from tests.unit.test_align_gps import SIZE, _centre_errors, _strip
from workers.algorithms.mosaic import alignment, apply_homography, plane_adjustment, refine_homographies


def _fixes(truth: dict[int, np.ndarray], sigma_px: float, seed: int = 5) -> dict[int, tuple[np.ndarray, float]]:
    rng = np.random.default_rng(seed)
    centre = np.array([[(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2]])
    return {k: (apply_homography(H, centre)[0] + rng.normal(0, sigma_px, 2), sigma_px) for k, H in truth.items()}


def test_sparse_and_dense_normal_equations_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    truth, ties, start = _strip(bias_rad=np.deg2rad(0.05))
    sizes = {k: SIZE for k in truth}
    fixes = _fixes(truth, 2.0)
    dense = refine_homographies(start, ties, 0, sizes, positions=fixes)
    monkeypatch.setattr(plane_adjustment, "DENSE_MAX_UNKNOWNS", 0)  # every problem sparse
    sparse = refine_homographies(start, ties, 0, sizes, positions=fixes)
    for k in truth:
        np.testing.assert_allclose(sparse[k], dense[k], rtol=0, atol=1e-7)
    assert _centre_errors(sparse, truth).max() < 4.0


def test_normal_equations_are_those_of_the_residuals(monkeypatch: pytest.MonkeyPatch) -> None:
    """J^T W J and J^T W r from the blocks equal those of a finite-difference Jacobian of ``residuals``."""
    truth, ties, start = _strip(bias_rad=np.deg2rad(0.05))
    captured: dict[str, Any] = {}

    def capture(residuals: Any, normal_equations: Any, x0: np.ndarray, f_scale: float) -> np.ndarray:
        captured.update(residuals=residuals, normal_equations=normal_equations, n=len(x0))
        return x0

    monkeypatch.setattr(alignment, "levenberg_marquardt", capture)
    refine_homographies(start, ties, 0, {k: SIZE for k in truth}, positions=_fixes(truth, 2.0))
    residuals, normal_equations, n = captured["residuals"], captured["normal_equations"], captured["n"]
    x = np.random.default_rng(2).normal(0, 1e-4, n)
    r = residuals(x)
    step = 1e-7
    J = np.column_stack([(residuals(x + step * e) - r) / step for e in np.eye(n)])
    f = 2.0
    w = 1.0 / np.sqrt(1.0 + (r / f) ** 2)
    normal, gradient = normal_equations(x, f)
    np.testing.assert_allclose(np.asarray(normal), (J.T * w) @ J, rtol=2e-4, atol=1e-6 * np.abs(normal).max())
    np.testing.assert_allclose(gradient, (J.T * w) @ r, rtol=2e-4, atol=1e-6 * np.abs(gradient).max())


def test_the_log_scale_and_its_derivative() -> None:
    # a frame 2000 px wide (1000 px per normalised unit) mapped at 0.5 plane px per px, squeezed 2 % in y
    M = np.array([[[500.0, 0.0, 7.0], [0.0, 490.0, 3.0], [0.0, 0.0, 1.0]]])
    np.testing.assert_allclose(plane_adjustment.log_scale(M, np.array([1000.0])), [0.5 * np.log(0.5 * 0.49)])
    rng = np.random.default_rng(0)
    A = np.eye(3) + rng.normal(0, 0.1, (5, 3, 3))
    D = rng.normal(0, 0.05, (5, 8))
    unit = rng.uniform(100, 1000, 5)

    def corrected(D: np.ndarray) -> np.ndarray:
        return A @ (np.eye(3) + np.pad(D, ((0, 0), (0, 1))).reshape(-1, 3, 3))

    value, analytic = plane_adjustment.log_scale_derivative(corrected(D), A, unit)
    np.testing.assert_allclose(value, plane_adjustment.log_scale(corrected(D), unit), rtol=1e-12)
    numeric = np.stack(
        [
            (plane_adjustment.log_scale(corrected(D + e), unit) - plane_adjustment.log_scale(corrected(D - e), unit))
            / 2e-6
            for e in 1e-6 * np.eye(8)
        ],
        axis=-1,
    )
    np.testing.assert_allclose(analytic, numeric, atol=1e-8)
