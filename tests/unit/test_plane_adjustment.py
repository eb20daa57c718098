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
