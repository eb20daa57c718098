"""The report's GPS drift: what a mosaic strays from its route, told apart from the fixes' own noise."""

from __future__ import annotations

import numpy as np

from workers.stages.georeference import gps_drift_m


def _route(n: int) -> np.ndarray:
    """(n, 2) UTM m: fixes 90 m apart heading north-east, out of order (drift follows the route, not the list)."""
    along = np.arange(n) * 90.0
    return np.random.default_rng(1).permutation(np.column_stack([along, along]) / np.sqrt(2) + [650_000, 5_200_000])


def test_noise_alone_is_not_drift() -> None:
    fixes = _route(60)
    misses = np.random.default_rng(2).normal(0, 1.0, fixes.shape)  # 1 m fixes, an unbent mosaic
    drift = gps_drift_m(fixes, misses)
    assert drift is not None and drift < 1.0  # means of 10 misses: about 0.4 m, never the bend below


def test_a_bend_between_fixes_is_drift() -> None:
    fixes = _route(60)
    along = (fixes - fixes.mean(axis=0)) @ np.array([1, 1]) / np.sqrt(2)
    across = np.array([1, -1]) / np.sqrt(2)
    # the mosaic bows 3 m sideways at the route's middle, over the same 1 m noise
    bow = 3.0 * (1 - (along / np.abs(along).max()) ** 2)
    misses = bow[:, None] * across + np.random.default_rng(2).normal(0, 1.0, fixes.shape)
    drift = gps_drift_m(fixes, misses)
    assert drift is not None and 2.3 < drift < 3.7


def test_too_few_fixes_give_no_drift() -> None:
    assert gps_drift_m(_route(19), np.zeros((19, 2))) is None
    assert gps_drift_m(_route(20), np.zeros((20, 2))) == 0.0
