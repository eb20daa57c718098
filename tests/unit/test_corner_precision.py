"""The frames' corner precision a strip's adjustment reports (``alignment.corner_sigmas``): the standard errors its
normal equations propagate, checked against the scatter of many solutions from noise drawn as the weights assume.

Each draw is one Gauss-Newton step from the truth of the strip in ``test_square_pixels`` (tie points with 0.1 px
noise, 1 m GPS fixes, the square-pixel prior), with the datum the adjustment's: the fixes, and the frames'
perspective rows averaging to zero. The scatter is taken about the draws' mean: measuring tie misses in the plane
lets a solution shrink the plane a little to shorten them (here by 0.15 %, set against 10 fixes 240 px apart; on a
305-frame strip of 1 m fixes 3e-6), a bias of the estimate and not part of its precision.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import csr_matrix

from tests.unit.test_square_pixels import SIZE, _strip
from workers.algorithms.mosaic import TiePoints, apply_homography, corner_sigmas, frame_corners, plane_adjustment
from workers.algorithms.mosaic.alignment import _mean_perspective, _normalised_points, _plane_problem
from workers.algorithms.mosaic.plane_adjustment import inverse_diagonal_blocks, point_derivative

TIE_NOISE_PX = 0.1
GPS_NOISE_PX = 1.0  # 1 m fixes on ground px of 1 m
SQUARE = 1e-4  # align_frames' default strip_square_pixels


def _draw(rng: np.random.Generator, truth: dict[int, np.ndarray], ties: dict, centres: np.ndarray) -> tuple:
    """Tie points moved by noise in their second frame, fixes of the centres moved by theirs (sigma in tie units)."""
    noisy = {}
    for (i, j), t in ties.items():
        exact = apply_homography(np.linalg.inv(truth[j]) @ truth[i], t.points_i)
        noisy[(i, j)] = TiePoints(t.points_i, exact + rng.normal(0, TIE_NOISE_PX, exact.shape))
    weight = GPS_NOISE_PX / TIE_NOISE_PX
    return noisy, {k: (c + rng.normal(0, GPS_NOISE_PX, 2), weight) for k, c in enumerate(centres)}


def test_the_predicted_corner_errors_are_the_scatter_of_solutions() -> None:
    frames = 24
    rng = np.random.default_rng(7)
    homographies, _, ties, _ = _strip(4, count=frames)
    truth = {k: H / H[2, 2] for k, H in enumerate(homographies)}
    sizes = dict.fromkeys(truth, SIZE)
    centres = np.array([apply_homography(truth[k], [[(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2]])[0] for k in truth])
    shape_weight = TIE_NOISE_PX / SQUARE
    noisy, fixes = _draw(rng, truth, ties, centres)
    sigma = corner_sigmas(truth, noisy, sizes, fixes, shape_weight)  # scaled by this draw's scatter
    assert sorted(sigma) == list(range(frames))
    misses = []
    for _ in range(60):
        noisy, fixes = _draw(rng, truth, ties, centres)
        built = _plane_problem(truth, noisy, None, sizes, 0.0, fixes, shape_weight)
        assert built is not None
        problem, order, norms = built
        normal, gradient = problem.normal_equations(np.zeros(8 * frames), 2.0)
        datum = _mean_perspective(problem.lift)
        bordered = np.block([[normal, datum.T], [datum, np.zeros((2, 2))]])
        step = np.linalg.solve(bordered, np.concatenate([-gradient, [0.0, 0.0]]))[: 8 * frames]
        corners = np.concatenate([_normalised_points(norms[k], frame_corners(*SIZE)) for k in order])
        derivative = point_derivative(np.repeat(problem.lift, 4, axis=0), corners)
        misses.append(np.einsum("nck,nk->nc", derivative, np.repeat(step.reshape(-1, 8), 4, axis=0)))
    misses_ = np.array(misses)  # (draws, 4 corners x frames, 2)
    scatter = np.sqrt(np.sum((misses_ - misses_.mean(axis=0)) ** 2, axis=2).mean(axis=0))  # per corner, RMS
    found = scatter.reshape(frames, 4).max(axis=1)
    predicted = np.array([sigma[k] for k in range(frames)])
    ratio = found / predicted
    # 60 draws measure an RMS to about 9 %; the frames' errors are correlated, so the mean ratio is not
    # much better known than one frame's
    assert 0.8 < np.sqrt(np.mean(ratio**2)) < 1.25, ratio
    # the strip's ends, whose far halves no other frame sees, are the least well known (on so short a strip the
    # datum, the fixes' rotation and scale over 24 x 240 px, is most of every frame's error)
    assert predicted.max() in (predicted[0], predicted[-1]) and min(predicted[0], predicted[-1]) > np.median(predicted)


def test_no_fixes_no_precision() -> None:
    homographies, _, ties, _ = _strip(5, count=6)
    truth = {k: H / H[2, 2] for k, H in enumerate(homographies)}
    assert corner_sigmas(truth, ties, dict.fromkeys(truth, SIZE), {}, TIE_NOISE_PX / SQUARE) == {}


def test_a_frame_no_tie_point_joins_is_left_out() -> None:
    # its neighbour was rejected: GPS and the prior alone leave 4 of its 8 parameters unobserved, and an inverse
    # taken anyway gave it 3e11 px and moved the others'
    homographies, _, ties, _ = _strip(6, count=12)
    truth = {k: H / H[2, 2] for k, H in enumerate(homographies)}
    centres = np.array([apply_homography(truth[k], [[(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2]])[0] for k in truth])
    fixes = {k: (c, GPS_NOISE_PX / TIE_NOISE_PX) for k, c in enumerate(centres)}
    sizes = dict.fromkeys(truth, SIZE)
    whole = corner_sigmas(truth, ties, sizes, fixes, TIE_NOISE_PX / SQUARE)
    cut = {pair: t for pair, t in ties.items() if pair != (0, 1)}
    left = corner_sigmas(truth, cut, sizes, fixes, TIE_NOISE_PX / SQUARE)
    assert sorted(left) == list(range(1, 12))
    assert max(left.values()) < 3 * max(whole.values()), (left, whole)


@pytest.mark.parametrize("sparse", [False, True])
def test_an_unobserved_parameter_is_refused(sparse: bool) -> None:
    # 15 observations of 16 parameters: one combination of them is unobserved (the factor may exist in
    # floating point; its inverse would be noise)
    A = np.random.default_rng(1).normal(size=(16, 15))
    normal = A @ A.T
    with pytest.raises(np.linalg.LinAlgError):
        inverse_diagonal_blocks(csr_matrix(normal) if sparse else normal)
    normal[3, 3] = np.nan
    with pytest.raises(np.linalg.LinAlgError):
        inverse_diagonal_blocks(csr_matrix(normal) if sparse else normal)


@pytest.mark.parametrize("constrained", [False, True])
@pytest.mark.parametrize("max_band", [plane_adjustment.MAX_BAND, 0])  # the banded recurrence, then SuperLU's
def test_diagonal_blocks_of_the_inverse_sparse_as_dense(
    constrained: bool, max_band: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # a strip's normal matrix: each frame's 8 parameters tied to its next two frames', the frames numbered out of
    # flight order (as after frames were dropped or a route turned), so the band shows only once reordered
    monkeypatch.setattr(plane_adjustment, "MAX_BAND", max_band)
    rng = np.random.default_rng(3)
    frames = 40
    n = 8 * frames
    along = rng.permutation(frames)  # the frame at each place along the strip
    normal = np.zeros((n, n))
    for place in range(frames - 2):
        rows = (8 * along[place : place + 3, None] + np.arange(8)).ravel()
        A = rng.normal(size=(24, 24))
        normal[np.ix_(rows, rows)] += A @ A.T
    normal += np.eye(n)
    constraints = rng.normal(size=(2, n)) if constrained else None
    full = normal if constraints is None else np.block([[normal, constraints.T], [constraints, np.zeros((2, 2))]])
    inverse = np.linalg.inv(full)[:n, :n]
    expected = np.stack([inverse[8 * b : 8 * b + 8, 8 * b : 8 * b + 8] for b in range(frames)])
    np.testing.assert_allclose(inverse_diagonal_blocks(normal, constraints), expected, rtol=1e-9, atol=1e-12)
    taken = plane_adjustment._banded_inverse_blocks(csr_matrix(normal), constraints, 8) is not None
    assert taken == bool(max_band)  # reordered, the band is 3 frames (23 rows) wide; in frame order, 39
    # a few columns at a time, as a long strip's are solved by SuperLU
    sparse = inverse_diagonal_blocks(csr_matrix(normal), constraints, columns=24)
    np.testing.assert_allclose(sparse, expected, rtol=1e-7, atol=1e-10)
