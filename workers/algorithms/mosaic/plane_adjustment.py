"""The joint least-squares adjustment of frame -> plane homographies over every tie point at once (the
homography variant of bundle adjustment: Brown & Lowe 2007; OpenCV ``detail::BundleAdjusterReproj``),
vectorised over all observations: residuals, analytic derivatives and the normal equations come from a
few array operations per iteration, whatever the number of pairs.

Frame k maps its pixels to the plane by ``A_k (I + D_k) N_k``: ``N_k`` normalises its pixels (centre 0,
half-size 1), ``A_k`` is the starting homography in those units (fixed) and ``D_k`` (eight parameters, its
[2, 2] entry held at 0) is what the adjustment moves. A held root frame has no ``D``: it defines the plane.
A prior (``shape_weight``) may hold each free frame's pixels square at its centre (:func:`aspect_shear`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, TypeAlias

import numpy as np
from threadpoolctl import threadpool_limits

if TYPE_CHECKING:
    from scipy.sparse import csr_matrix

# d(C q)/d(params): parameter m of D (row-major, D[2, 2] = 0) scales component ROW[m] of q by q[COL[m]]
_ROW = np.array([0, 0, 0, 1, 1, 1, 2, 2])
_COL = np.array([0, 1, 2, 0, 1, 2, 0, 1])
PARAMETER_ROW, PARAMETER_COL = _ROW, _COL  # for the derivatives alignment.py takes of the same parameters
DENSE_MAX_UNKNOWNS = 2400  # normal equations up to this size (300 frames) are solved densely, beyond sparsely

# SciPy's sparse matrices only past DENSE_MAX_UNKNOWNS, imported there: SciPy's linear algebra adds ~50 MiB to a
# worker that composes a drone flight (more than its data: OpenCV's stitcher peaks at 134 MiB on budapest1-6)
Normal: TypeAlias = "np.ndarray | csr_matrix"


@dataclass
class PlaneProblem:
    """Every observation of the adjustment as flat arrays.

    Frames are numbered 0..F-1 here; ``slot[f]`` is frame f's block of eight parameters, -1 for the root.

    Attributes
    ----------
    lift : (F, 3, 3) float64, ``A_f``.
    slot : (F,) int64.
    q_i, q_j : (N, 3) float64 normalised homogeneous tie points of the two frames of each observation.
    f_i, f_j : (N,) int64 their frames.
    starts : (P,) int64 first observation of each pair (a pair's observations are contiguous).
    q_gps : (A, 3) float64 normalised centre of each frame with a GPS position; ``f_gps`` (A,) its frame,
        ``xy_gps`` (A, 2) the plane position and ``w_gps`` (A,) one over its sigma, 1/plane px.
    unit_px : (F,) float64 each frame's pixels per normalised unit. A tie point's miss in the plane is divided
        by its two frames' scale (plane px per frame px, the geometric mean of each frame's at its centre:
        :func:`log_scale`), so that it is counted in the photos' own pixels, where the points were measured.
        Counted in plane px, a frame that shrinks shrinks its points' noise with it: every tie point pulls its
        frames smaller by its noise's variance, and where tie points hold a frame's scale only loosely (a long
        strip's, through its frames' along-track tilt) the pulls add up: a 60-frame 75000-px strip with 6400
        tie points per pair and exact fixes came out with corners 3.6 px RMS off whatever the points' noise (0.2
        px counted in the photos' pixels), and more tie points made a strip worse.
    perspective_damping : weight of each free frame's two perspective parameters against the start, 1/unit.
    """

    lift: np.ndarray
    slot: np.ndarray
    q_i: np.ndarray
    q_j: np.ndarray
    f_i: np.ndarray
    f_j: np.ndarray
    starts: np.ndarray
    q_gps: np.ndarray
    f_gps: np.ndarray
    xy_gps: np.ndarray
    w_gps: np.ndarray
    unit_px: np.ndarray
    perspective_damping: float
    shape_weight: float = 0.0
    _dh: tuple[np.ndarray, np.ndarray] | None = field(default=None, init=False, repr=False)

    @property
    def n_free(self) -> int:
        return int((self.slot >= 0).sum())

    def perspective(self) -> np.ndarray:
        """(2 n_free,) int: the perspective parameters (D[2, 0], D[2, 1]) of every free frame."""
        return (8 * np.arange(self.n_free)[:, None] + np.array([6, 7])).ravel()

    def _lifted_derivatives(self) -> tuple[np.ndarray, np.ndarray]:
        """:func:`_lifted` of both sides of every tie point: they do not change while the parameters do."""
        if self._dh is None:
            self._dh = _lifted(self.lift[self.f_i], self.q_i), _lifted(self.lift[self.f_j], self.q_j)
        return self._dh

    def corrections(self, params: np.ndarray) -> np.ndarray:
        """(F, 3, 3) ``I + D_f`` (the identity for the root)."""
        d = np.zeros((len(self.slot), 9))
        free = self.slot >= 0
        d[free, :8] = params.reshape(-1, 8)[self.slot[free]]
        return np.eye(3) + d.reshape(-1, 3, 3)

    def residuals(self, params: np.ndarray) -> np.ndarray:
        """Tie-point misses in the plane, in their photos' pixels (x, y per point: ``unit_px``), the GPS misses over
        their sigmas, then the damped perspective parameters: the vector whose robust norm is minimised."""
        M = self.lift @ self.corrections(params)
        miss = _project(M[self.f_i], self.q_i)[0] - _project(M[self.f_j], self.q_j)[0]
        miss /= self._per_point(self._pair_scale(log_scale(M, self.unit_px)))[:, None]
        gps = self.w_gps[:, None] * (_project(M[self.f_gps], self.q_gps)[0] - self.xy_gps)
        return np.concatenate(
            [miss.ravel(), gps.ravel(), self.perspective_damping * params[self.perspective()], self._shape(M).ravel()]
        )

    def variance_factor(self, params: np.ndarray, f_scale: float, conditions: int = 0) -> float:
        """The a posteriori variance of unit weight at ``params`` (a solution): the IRLS-weighted squared residuals
        over the redundancy, observations less unknowns plus ``conditions`` (a datum's constraints; the damping
        counts only when it weighs). 1 when every observation's weight was one over its true variance; the
        parameters' covariance is it times ``normal^-1``. NaN with no redundancy."""
        r = self.residuals(params)
        observations = len(r) - (0 if self.perspective_damping else 2 * self.n_free)
        redundancy = observations - 8 * self.n_free + conditions
        return float(np.sum(_irls(r, f_scale) * r**2) / redundancy) if redundancy > 0 else float("nan")

    def _pair_scale(self, log_scales: np.ndarray) -> np.ndarray:
        """(P,) each pair's plane px per frame px: the geometric mean of its two frames' scales."""
        first = self.starts
        return np.exp(0.5 * (log_scales[self.f_i[first]] + log_scales[self.f_j[first]]))

    def _per_point(self, per_pair: np.ndarray) -> np.ndarray:
        """(N,) a pair's value for each of its tie points."""
        return np.repeat(per_pair, np.diff(np.append(self.starts, len(self.f_i))))

    def free_frames(self) -> np.ndarray:
        """(n_free,) int: the free frames in slot order."""
        return np.argsort(self.slot)[len(self.slot) - self.n_free :]

    def _shape(self, M: np.ndarray) -> np.ndarray:
        """(n_free, 2) each free frame's aspect and shear (:func:`aspect_shear`) times the prior's weight; (0, 2)
        without the prior."""
        if not self.shape_weight:
            return np.zeros((0, 2))
        return self.shape_weight * aspect_shear(M[self.free_frames()])

    def normal_equations(self, params: np.ndarray, f_scale: float) -> tuple[Normal, np.ndarray]:
        """``J^T W J`` and ``J^T W r`` at ``params``, W the soft-L1 IRLS weights ``1 / sqrt(1 + (r/f)^2)``,
        summed observation by observation into the 8 x 8 blocks of the frames they involve (the Jacobian
        itself is never formed)."""
        n = 8 * self.n_free
        C = self.corrections(params)
        M = self.lift @ C
        u_i, h_i = _project(M[self.f_i], self.q_i)
        u_j, h_j = _project(M[self.f_j], self.q_j)
        r = u_i - u_j
        dh_i, dh_j = self._lifted_derivatives()
        J_i = _derivative(dh_i, u_i, h_i)
        J_j = -_derivative(dh_j, u_j, h_j)
        # In the photos' pixels: r / s, s = exp((l_i + l_j) / 2) one number per pair (its frames' scales), so
        # d(r / s) = J / s - (r / s) (dl_i + dl_j) / 2 is summed pair by pair from the sums of J^T W J, J^T W r / s
        # and r^T W r / s^2 (30 frames, 38k tie points: 12 ms an iteration, 14.8 with the rank-one term per point;
        # 11.5 in plane px)
        centre = _centre_jacobian_derivative(M, self.lift)  # every frame's; the shape prior takes the free ones'
        log_scales, d_log = _log_scale_derivative(*centre, self.unit_px)
        s = self._pair_scale(log_scales)
        r = r / self._per_point(s)[:, None]
        w = _irls(r, f_scale)
        blocks = _BlockSum(self.n_free)
        pair_i, pair_j = self.slot[self.f_i[self.starts]], self.slot[self.f_j[self.starts]]
        # pair by pair: one (2n, 8)^T (2n, 8) product per block, where per-point 8 x 8 products summed
        # afterwards cost 4x as much
        ends = np.append(self.starts[1:], len(r))
        wi, wj = (J_i * w[:, :, None]).reshape(-1, 16), (J_j * w[:, :, None]).reshape(-1, 16)
        products = (
            np.stack(
                [
                    _pair_products(wi[a:b].reshape(-1, 8), wj[a:b].reshape(-1, 8), J_i[a:b], J_j[a:b])
                    for a, b in zip(self.starts, ends, strict=True)
                ]
            )
            / (s**2)[:, None, None, None]
        )  # (P, 4, 8, 8): ii, jj, ij, ji
        a_i, a_j = (
            np.add.reduceat(np.einsum("nck,nc->nk", J, w * r), self.starts, axis=0) / s[:, None] for J in (J_i, J_j)
        )
        c = np.add.reduceat((w * r * r).sum(axis=1), self.starts)[:, None, None]
        l_i, l_j = d_log[self.f_i[self.starts]], d_log[self.f_j[self.starts]]  # (P, 8)

        def outer(x: np.ndarray, y: np.ndarray) -> np.ndarray:
            return x[:, :, None] * y[:, None, :]

        for k, (x, y) in enumerate(((a_i, l_i), (a_j, l_j))):
            products[:, k] += 0.25 * c * outer(y, y) - 0.5 * (outer(x, y) + outer(y, x))
        products[:, 2] += 0.25 * c * outer(l_i, l_j) - 0.5 * (outer(a_i, l_j) + outer(l_i, a_j))
        products[:, 3] = products[:, 2].transpose(0, 2, 1)
        for k, (sa, sb) in enumerate(((pair_i, pair_i), (pair_j, pair_j), (pair_i, pair_j), (pair_j, pair_i))):
            blocks.add(sa, sb, products[:, k])
        gradient = np.zeros((self.n_free + 1, 8))  # the last row collects the root's, which is dropped
        for slots, a, dl in ((pair_i, a_i, l_i), (pair_j, a_j, l_j)):
            np.add.at(gradient, slots, a - 0.5 * c[:, :, 0] * dl)
        if len(self.f_gps):
            u, h = _project(M[self.f_gps], self.q_gps)
            r_gps = self.w_gps[:, None] * (u - self.xy_gps)
            J = self.w_gps[:, None, None] * _derivative(_lifted(self.lift[self.f_gps], self.q_gps), u, h)
            w_gps, s = _irls(r_gps, f_scale), self.slot[self.f_gps]
            blocks.add(s, s, _weighted_products(J, w_gps, J))
            np.add.at(gradient, s, np.einsum("nck,nc->nk", J, w_gps * r_gps))
        # the perspective damping: one residual per damped parameter, its derivative the damping itself
        damped_at = self.perspective()
        damped = self.perspective_damping * params[damped_at]
        w_damped = _irls(damped, f_scale)
        if self.shape_weight:
            free = self.free_frames()
            shape, d_shape = _aspect_shear_derivative(centre[0][free], centre[1][free])
            r_shape, J_shape = self.shape_weight * shape, self.shape_weight * d_shape
            w_shape, slots = _irls(r_shape, f_scale), self.slot[free]
            blocks.add(slots, slots, _weighted_products(J_shape, w_shape, J_shape))
            np.add.at(gradient, slots, np.einsum("nck,nc->nk", J_shape, w_shape * r_shape))
        flat = gradient[:-1].ravel()
        flat[damped_at] += self.perspective_damping * w_damped * damped
        diagonal = np.zeros(n)
        diagonal[damped_at] = self.perspective_damping**2 * w_damped
        return blocks.matrix(diagonal), flat


class _BlockSum:
    """8 x 8 blocks summed by (row slot, column slot); slot -1 (the root frame) is dropped."""

    def __init__(self, n_free: int) -> None:
        self.n_free = n_free
        self.dense = np.zeros((n_free, n_free, 8, 8)) if 8 * n_free <= DENSE_MAX_UNKNOWNS else None
        self.keys: list[np.ndarray] = []
        self.values: list[np.ndarray] = []

    def add(self, rows: np.ndarray, cols: np.ndarray, blocks: np.ndarray) -> None:
        keep = (rows >= 0) & (cols >= 0)
        if self.dense is not None:
            np.add.at(self.dense, (rows[keep], cols[keep]), blocks[keep])
        else:
            self.keys.append(np.column_stack([rows[keep], cols[keep]]))
            self.values.append(blocks[keep])

    def matrix(self, diagonal: np.ndarray) -> Normal:
        n = 8 * self.n_free
        if self.dense is not None:
            return self.dense.transpose(0, 2, 1, 3).reshape(n, n) + np.diag(diagonal)
        keys, values = np.concatenate(self.keys), np.concatenate(self.values)
        grid = np.arange(8)
        rows = (8 * keys[:, 0, None, None] + grid[None, :, None]) + np.zeros((1, 1, 8), np.int64)
        cols = (8 * keys[:, 1, None, None] + grid[None, None, :]) + np.zeros((1, 8, 1), np.int64)
        data = np.concatenate([values.ravel(), diagonal])
        index = (np.concatenate([rows.ravel(), np.arange(n)]), np.concatenate([cols.ravel(), np.arange(n)]))
        from scipy.sparse import csr_matrix  # see Normal

        return csr_matrix((data, index), shape=(n, n))  # duplicates are summed


def levenberg_marquardt(
    residuals: Callable[[np.ndarray], np.ndarray],
    normal_equations: Callable[[np.ndarray, float], tuple[Normal, np.ndarray]],
    x0: np.ndarray,
    f_scale: float,
    max_iterations: int = 100,
) -> np.ndarray:
    """Minimise ``sum rho(r_i^2 / f^2)`` with the soft-L1 ``rho(z) = 2 (sqrt(1 + z) - 1)`` by Levenberg-Marquardt
    on iteratively reweighted normal equations (Triggs et al. 2000, sec. 6; Marquardt's diagonal damping).

    ``normal_equations(x, f)`` gives ``J^T W J`` and ``J^T W r`` at ``x``. The normal matrix has 8 rows per free
    frame: factorised directly (Cholesky for a few hundred frames, a sparse LU beyond), a handful of
    iterations where an iterative trust-region solver needed hundreds of inner ones.
    """

    def cost(r: np.ndarray) -> float:
        return float(np.sum(2.0 * (np.sqrt(1.0 + (r / f_scale) ** 2) - 1.0)))

    # One BLAS thread: a few hundred unknowns factorise in well under a millisecond on one, while OpenBLAS's
    # threads spin-wait on a host whose cores are busy (measured on 2 busy cores: 30 ms against 0.6 ms).
    with threadpool_limits(limits=1, user_api="blas"):
        return _iterate(residuals, normal_equations, x0, f_scale, cost, max_iterations)


def _iterate(
    residuals: Callable[[np.ndarray], np.ndarray],
    normal_equations: Callable[[np.ndarray, float], tuple[Normal, np.ndarray]],
    x0: np.ndarray,
    f_scale: float,
    cost: Callable[[np.ndarray], float],
    max_iterations: int,
) -> np.ndarray:
    x, r = x0.copy(), residuals(x0)
    current, lam = cost(r), 1e-3
    for _ in range(max_iterations):
        normal, gradient = normal_equations(x, f_scale)
        diagonal = np.maximum(normal.diagonal(), 1e-12)
        while True:
            step = _solve(normal, lam * diagonal, -gradient)
            r_new = residuals(x + step)
            new = cost(r_new)
            if new < current or lam > 1e12:
                break
            lam *= 4.0
        if new >= current:
            break  # no step lowers the cost: converged
        x, r = x + step, r_new
        done = current - new < 1e-10 * current or np.abs(step).max() < 1e-12
        current, lam = new, max(lam / 3.0, 1e-9)
        if done:
            break
    return x


def _solve(normal: Normal, damping: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``(normal + diag(damping))^-1 rhs``: LAPACK's LU on a dense matrix (NumPy's: SciPy's Cholesky took 0.36 ms
    against 0.47 ms at 30 frames, 6.6 against 10.7 ms at 100, not worth SciPy's memory), SuperLU on a sparse one."""
    if isinstance(normal, np.ndarray):
        damped = normal + np.diag(damping)
        try:
            return np.linalg.solve(damped, rhs)
        except np.linalg.LinAlgError:  # singular in floating point: least squares instead
            return np.linalg.lstsq(damped, rhs, rcond=None)[0]
    from scipy.sparse import diags  # see Normal
    from scipy.sparse.linalg import spsolve

    return np.asarray(spsolve((normal + diags(damping)).tocsc(), rhs))


def inverse_diagonal_blocks(
    normal: Normal, constraints: np.ndarray | None = None, size: int = 8, columns: int = 512
) -> np.ndarray:
    """(n / size, size, size) the diagonal blocks of ``normal^-1`` (a parameter covariance, up to its residuals'
    variance); with ``constraints`` (c, n) ``C``, of the covariance with ``C x = 0`` held exactly (a datum): the
    top-left block of the bordered matrix ``[[N, C^T], [C, 0]]``'s inverse, ``N^-1 - Y M^-1 Y^T`` with
    ``Y = N^-1 C^T``, ``M = C Y`` (Förstner & Wrobel 2016, sec. 4.5).

    A dense matrix: LAPACK's Cholesky factor (the positive-definiteness check) and inverse. A sparse one whose
    blocks make a band once reordered (reverse Cuthill-McKee over the blocks: a strip's frames tie only to their
    next few): :func:`_banded_inverse_blocks`, time linear in n. Otherwise SuperLU on the bordered matrix, solved
    against ``columns`` unit vectors at a time with only the blocks kept (a 1600-frame route's whole inverse would
    be 1.3 GB). Raises ``np.linalg.LinAlgError`` when ``normal`` is not finite or, but for SuperLU's, not
    positive definite to ``MIN_PIVOT`` (a parameter nothing observes)."""
    n = normal.shape[0]
    c = 0 if constraints is None else len(constraints)
    values = normal if isinstance(normal, np.ndarray) else normal.data
    if not np.all(np.isfinite(values)):
        raise np.linalg.LinAlgError("the normal matrix is not finite")
    if isinstance(normal, np.ndarray):
        _check_pivots(np.linalg.cholesky(normal).diagonal() ** 2, normal.diagonal())
        inverse = np.linalg.inv(normal)
        index = np.arange(n).reshape(-1, size)
        blocks = inverse[index[:, :, None], index[:, None, :]]
        if c:
            Y = inverse @ constraints.T  # type: ignore[union-attr]
            Y_blocks = Y.reshape(-1, size, c)
            blocks -= Y_blocks @ np.linalg.inv(constraints @ Y) @ Y_blocks.transpose(0, 2, 1)  # type: ignore[operator]
        return blocks
    banded = _banded_inverse_blocks(normal, constraints, size)
    if banded is not None:
        return banded
    from scipy.sparse import bmat, csr_matrix  # see Normal
    from scipy.sparse.linalg import splu

    if c:
        border = csr_matrix(constraints)
        normal = bmat([[normal, border.T], [border, None]])
    try:
        factor = splu(normal.tocsc())
    except RuntimeError as error:  # SuperLU: "Factor is exactly singular"
        raise np.linalg.LinAlgError(str(error)) from error
    blocks = np.empty((n // size, size, size))
    step = max(columns // size, 1) * size
    for start in range(0, n, step):
        stop = min(start + step, n)
        unit = np.zeros((n + c, stop - start))
        unit[np.arange(start, stop), np.arange(stop - start)] = 1.0
        solved = factor.solve(unit)  # (n + c, stop - start): columns start..stop of the inverse
        for b in range(start // size, stop // size):
            blocks[b] = solved[b * size : (b + 1) * size, b * size - start : (b + 1) * size - start]
    return blocks


MIN_PIVOT = 1e-12  # a Cholesky pivot below this share of its diagonal entry: a parameter nothing observes


def _check_pivots(pivots: np.ndarray, diagonal: np.ndarray) -> None:
    """Raise ``np.linalg.LinAlgError`` when a Cholesky pivot (``u_ii^2``) is below ``MIN_PIVOT`` of its matrix's
    diagonal entry: the factor exists in floating point, the inverse would be noise (a frame no tie point
    joins to the others: a 1e11 px standard error)."""
    if np.any(pivots < MIN_PIVOT * np.maximum(diagonal, np.finfo(float).tiny)):
        raise np.linalg.LinAlgError("the normal matrix is singular: a parameter is not observed")


MAX_BAND = 256  # widest band (scalar rows) :func:`_banded_inverse_blocks` takes on: its window is this squared


def _banded_inverse_blocks(normal: csr_matrix, constraints: np.ndarray | None, size: int) -> np.ndarray | None:
    """:func:`inverse_diagonal_blocks` of a sparse positive definite ``normal`` by its banded Cholesky factor
    ``N = U^T U`` (LAPACK) and Takahashi's recurrence for the inverse's entries within the band (Takahashi, Fagan &
    Chin 1973; Erisman & Tinney 1975): row i of ``U Z = U^-T`` gives ``Z_ij = (delta_ij / u_ii - sum_k u_ik Z_kj)
    / u_ii``, bottom row first, each row needing only the window of Z the band spans. A datum ``C x = 0``
    subtracts ``Y M^-1 Y^T`` (``Y = N^-1 C^T``, ``M = C Y``). None when the band is wider than ``MAX_BAND``
    or the matrix is not positive definite without the datum (the bordered system then takes it); raises
    ``np.linalg.LinAlgError`` when a pivot is below ``MIN_PIVOT``."""
    from scipy.linalg import cho_solve_banded, cholesky_banded
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    n = normal.shape[0]
    coo = coo_matrix(normal)
    coo.sum_duplicates()
    pattern = coo_matrix((np.ones(coo.nnz), (coo.row // size, coo.col // size)), shape=(n // size, n // size))
    order = reverse_cuthill_mckee(pattern.tocsr(), symmetric_mode=True)  # blocks, new -> old
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    row = rank[coo.row // size] * size + coo.row % size
    col = rank[coo.col // size] * size + coo.col % size
    width = int(np.abs(row - col).max(initial=0))
    if width > MAX_BAND:
        return None
    upper = row <= col
    band = np.zeros((width + 1, n))  # LAPACK's upper band storage: band[width + i - j, j] = N[i, j]
    band[width + row[upper] - col[upper], col[upper]] = coo.data[upper]
    try:
        factor = cholesky_banded(band, lower=False)
    except np.linalg.LinAlgError:
        return None
    _check_pivots(factor[width] ** 2, band[width])
    m = max(width, size)
    window = np.zeros((m, m))  # Z over rows/columns i + 1 .. i + m (zero past the end)
    lifted = np.zeros((m, n + m))  # U[i, i + d] at lifted[d - 1, i]: the factor's rows as columns
    for d in range(1, width + 1):
        lifted[d - 1, : n - d] = factor[width - d, d:]
    diagonal = factor[width]
    blocks = np.empty((n // size, size, size))
    for i in range(n - 1, -1, -1):
        u = lifted[:, i]
        z = -(window @ u) / diagonal[i]
        shifted = np.empty_like(window)
        shifted[0, 0] = (1.0 / diagonal[i] - u @ z) / diagonal[i]
        shifted[0, 1:] = shifted[1:, 0] = z[:-1]
        shifted[1:, 1:] = window[:-1, :-1]
        window = shifted
        if i % size == 0:
            blocks[i // size] = window[:size, :size]
    if constraints is not None and len(constraints):
        flat = (order[:, None] * size + np.arange(size)).ravel()  # new scalar index -> old
        reordered = constraints[:, flat]
        Y = cho_solve_banded((factor, False), reordered.T)  # (n, c)
        M_inv = np.linalg.inv(reordered @ Y)
        Y_blocks = Y.reshape(-1, size, len(constraints))
        blocks -= Y_blocks @ M_inv @ Y_blocks.transpose(0, 2, 1)
    out = np.empty_like(blocks)
    out[order] = blocks
    return out


def point_derivative(M: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(n, 2, 8) derivative of the plane points of normalised points ``q`` (n, 3) through ``M (I + D)`` ((n, 3, 3)
    ``M``) by the eight parameters of ``D``, at ``D = 0``."""
    u, h = _project(M, q)
    return _derivative(_lifted(M, q), u, h)


def aspect_shear(M: np.ndarray) -> np.ndarray:
    """(n, 2) aspect ``(a - d) / (a + d)`` and shear ``(b + c) / (a + d)`` of the Jacobian ``[[a, b], [c, d]]`` of
    each (n, 3, 3) normalised frame -> plane map ``M`` at the frame's centre (normalised (0, 0)). The
    normalisation is isotropic, so these are the frame pixels' own: zero for square pixels."""
    return _aspect_shear_of(_centre_jacobian(M)[2])


def aspect_shear_derivative(M: np.ndarray, lift: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`aspect_shear` of ``M = A (I + D)`` ((n, 3, 3) ``lift`` ``A``) and its (n, 2, 8) derivative by the
    eight parameters of ``D``."""
    return _aspect_shear_derivative(*_centre_jacobian_derivative(M, lift))


def log_scale(M: np.ndarray, unit_px: np.ndarray) -> np.ndarray:
    """(n,) log of each (n, 3, 3) normalised frame -> plane map ``M``'s scale at the frame's centre, plane px per
    frame px: half the log of its Jacobian's determinant, less the log of the frame's ``unit_px``."""
    return _log_scale(_centre_jacobian(M)[2], unit_px)


def log_scale_derivative(M: np.ndarray, lift: np.ndarray, unit_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`log_scale` of ``M = A (I + D)`` ((n, 3, 3) ``lift`` ``A``) and its (n, 8) derivative by the eight
    parameters of ``D``."""
    return _log_scale_derivative(*_centre_jacobian_derivative(M, lift), unit_px)


def _aspect_shear_of(J: np.ndarray) -> np.ndarray:
    """(n, 2) :func:`aspect_shear` of the (n, 2, 2) Jacobians ``J``."""
    trace = J[:, 0, 0] + J[:, 1, 1]
    return np.column_stack([J[:, 0, 0] - J[:, 1, 1], J[:, 0, 1] + J[:, 1, 0]]) / trace[:, None]


def _aspect_shear_derivative(J: np.ndarray, dJ: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`aspect_shear_derivative` from the centre's Jacobians ``J`` (n, 2, 2) and their derivatives ``dJ``
    (n, 8, 2, 2)."""
    value = _aspect_shear_of(J)
    d_trace = dJ[:, :, 0, 0] + dJ[:, :, 1, 1]
    d_value = np.stack([dJ[:, :, 0, 0] - dJ[:, :, 1, 1], dJ[:, :, 0, 1] + dJ[:, :, 1, 0]], axis=1)  # (n, 2, 8)
    trace = J[:, 0, 0] + J[:, 1, 1]
    return value, (d_value - value[:, :, None] * d_trace[:, None, :]) / trace[:, None, None]


def _log_scale(J: np.ndarray, unit_px: np.ndarray) -> np.ndarray:
    return 0.5 * np.log(np.abs(np.linalg.det(J))) - np.log(unit_px)


def _log_scale_derivative(J: np.ndarray, dJ: np.ndarray, unit_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`log_scale_derivative` from ``J`` and ``dJ`` as :func:`_aspect_shear_derivative` takes them:
    ``d log det J = trace(J^-1 dJ)``."""
    return _log_scale(J, unit_px), 0.5 * np.einsum("nab,nmba->nm", np.linalg.inv(J), dJ)


def _centre_jacobian_derivative(M: np.ndarray, lift: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (n, 2, 2) Jacobian ``J`` of each ``M = A (I + D)`` at its frame's centre and its (n, 8, 2, 2)
    derivative by the eight parameters of ``D``."""
    u, h, J = _centre_jacobian(M)
    # d M / d m: column COL[m] of M gains column ROW[m] of A, the others nothing
    dM = np.zeros((len(M), 8, 3, 3))
    dM[:, np.arange(8), :, _COL] = lift[:, :, _ROW].transpose(2, 0, 1)  # indexed (8, n, 3)
    dh = dM[:, :, :, 2]  # (n, 8, 3)
    du = (dh[:, :, :2] - u[:, None, :] * dh[:, :, 2:]) / h[:, None, 2:]
    dN = dM[:, :, :2, :2] - du[:, :, :, None] * M[:, None, 2:3, :2] - u[:, None, :, None] * dM[:, :, 2:3, :2]
    return J, (dN - J[:, None] * dh[:, :, 2, None, None]) / h[:, 2, None, None, None]


def _centre_jacobian(M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The centre's plane point ``u`` (n, 2), its homogeneous ``h`` (n, 3) and the Jacobian ``J`` (n, 2, 2) there
    of each (n, 3, 3) normalised frame -> plane map ``M``."""
    h = M[:, :, 2]
    u = h[:, :2] / h[:, 2:]
    J = (M[:, :2, :2] - u[:, :, None] * M[:, 2:3, :2]) / h[:, 2, None, None]
    return u, h, J


def _pair_products(wi: np.ndarray, wj: np.ndarray, J_i: np.ndarray, J_j: np.ndarray) -> np.ndarray:
    """(4, 8, 8) blocks ii, jj, ij, ji of one pair's normal matrix, from its weighted (2n, 8) derivatives
    ``wi``, ``wj`` and its (n, 2, 8) derivatives."""
    Ji, Jj = J_i.reshape(-1, 8), J_j.reshape(-1, 8)
    return np.stack([wi.T @ Ji, wj.T @ Jj, wi.T @ Jj, wj.T @ Ji])


def _weighted_products(Ja: np.ndarray, w: np.ndarray, Jb: np.ndarray) -> np.ndarray:
    """(n, 8, 8) ``Ja[k]^T diag(w[k]) Jb[k]`` of (n, 2, 8) derivatives and (n, 2) weights."""
    return np.matmul((Ja * w[:, :, None]).transpose(0, 2, 1), Jb)


def _irls(r: np.ndarray, f_scale: float) -> np.ndarray:
    """Soft-L1 IRLS weight ``rho'(z)`` of every residual, same shape."""
    return 1.0 / np.sqrt(1.0 + (r / f_scale) ** 2)


def _project(M: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plane points (n, 2) of normalised points ``q`` (n, 3) through the (n, 3, 3) ``M``, and their
    homogeneous (n, 3)."""
    h = np.einsum("nij,nj->ni", M, q)
    return h[:, :2] / h[:, 2:3], h


def _lifted(A: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(n, 3, 8) ``A d(C q)/dm`` of (n, 3, 3) ``A`` and (n, 3) ``q`` for the eight parameters m of ``C = I + D``:
    homogeneous, and independent of ``C``."""
    return A[:, :, _ROW] * q[:, None, _COL]


def _derivative(dh: np.ndarray, u: np.ndarray, h: np.ndarray) -> np.ndarray:
    """(n, 2, 8) derivative of the plane points ``u`` = dehomogenised ``h`` (both (n, .)) by the eight
    parameters of ``C``, from their :func:`_lifted` homogeneous derivatives ``dh``."""
    return (dh[:, :2, :] - u[:, :, None] * dh[:, 2:3, :]) / h[:, 2, None, None]
