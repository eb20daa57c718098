"""Put every frame into one plane: a maximum spanning tree of pairwise homographies, then a global
least-squares adjustment of all frame homographies over all tie points (the homography variant of
bundle adjustment used by Brown & Lowe 2007 and OpenCV's ``detail::BundleAdjusterReproj``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix

Pair = tuple[int, int]


@dataclass
class TiePoints:
    """Matched points of one frame pair: ``points_j ~ H_ij points_i``; (N, 2) float64 pixel (x, y)."""

    points_i: np.ndarray
    points_j: np.ndarray


def apply_homography(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map (N, 2) pixel (x, y) points through a (3, 3) homography."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    q = pts @ H[:, :2].T + H[:, 2]
    return q[:, :2] / q[:, 2:3]


def spanning_tree(n_frames: int, weights: dict[Pair, float]) -> tuple[int, dict[int, int]]:
    """Maximum spanning tree (Prim) of the frame graph, rooted at its best-connected frame.

    Parameters
    ----------
    weights : (i, j) with i < j -> edge weight (e.g. inlier count); absent pairs are not connected.

    Returns
    -------
    root : the frame with the largest total weight in the largest connected component.
    parent : frame -> its parent in the tree, for every frame of that component except the root.
    """
    adj: dict[int, dict[int, float]] = {k: {} for k in range(n_frames)}
    for (i, j), w in weights.items():
        adj[i][j] = adj[j][i] = w
    strength = {k: sum(adj[k].values()) for k in adj}
    trees = [_prim(start, adj) for start in range(n_frames)]
    largest = max(len(t) for t in trees)
    root = max((k for k in range(n_frames) if len(trees[k]) == largest), key=lambda k: (strength[k], -k))
    return root, trees[root]


def _prim(root: int, adj: dict[int, dict[int, float]]) -> dict[int, int]:
    parent: dict[int, int] = {}
    in_tree = {root}
    frontier = {j: (w, root) for j, w in adj[root].items()}
    while frontier:
        j = max(frontier, key=lambda k: frontier[k][0])
        parent[j] = frontier.pop(j)[1]
        in_tree.add(j)
        for k, w in adj[j].items():
            if k not in in_tree and (k not in frontier or w > frontier[k][0]):
                frontier[k] = (w, j)
    return parent


def chain_homographies(root: int, parent: dict[int, int], pairwise: dict[Pair, np.ndarray]) -> dict[int, np.ndarray]:
    """Frame -> root-plane homographies by composing pairwise ones along the tree.

    ``pairwise[(i, j)]`` maps frame i pixels to frame j pixels (i < j); its inverse is used as needed.
    """
    result = {root: np.eye(3)}

    def to_root(k: int) -> np.ndarray:
        if k not in result:
            p = parent[k]
            H_kp = pairwise[(k, p)] if (k, p) in pairwise else np.linalg.inv(pairwise[(p, k)])
            H = to_root(p) @ H_kp
            result[k] = H / H[2, 2]
        return result[k]

    for k in parent:
        to_root(k)
    return result


def refine_homographies(
    initial: dict[int, np.ndarray],
    ties: dict[Pair, TiePoints],
    root: int,
    frame_sizes: dict[int, tuple[int, int]],
    loss_scale_px: float = 2.0,
    perspective_damping: float = 1000.0,
    positions: dict[int, tuple[np.ndarray, float]] | None = None,
) -> dict[int, np.ndarray]:
    """Adjust all frame->plane homographies jointly so that every tie point pair meets in the plane.

    The root frame is held fixed (it defines the plane). Each other frame is parametrised by a
    correction ``I + D`` in its own normalised coordinates (centre 0, half-size 1), which keeps the
    eight unknowns per frame on the same scale. A soft-L1 loss down-weights residual outliers. The
    derivatives are analytic and the normal equations (8 unknowns per frame) are solved directly by
    Levenberg-Marquardt: 1.4 s for 30 frames and 40k tie points, where scipy's ``least_squares`` with
    finite differences over a sparsity pattern took 167 s and stopped at its evaluation limit.

    The tie-point cost is nearly flat along one mode, the slow "bending" of a chain of frames through
    their perspective terms: on a synthetic strip the true solution costs more than one bent by 3 px,
    because sub-pixel keypoint biases are enough to choose the bend. ``perspective_damping`` ties each
    frame's perspective correction to the spanning-tree estimate (measured directly between overlapping
    frames): a correction of 1/damping in normalised units costs as much as a 1 px tie residual.

    ``positions`` holds what GPS says about a frame: where its centre lies in the plane and how sure that
    is, ``(xy (2,) plane px, sigma px)``. Each is one more observation, its miss divided by sigma, so a
    long strip cannot bend further than its GPS allows (tie points alone constrain a chain's shape only
    locally). The root frame is fixed: its position only matters through the plane's placement.

    Parameters
    ----------
    initial : frame -> (3, 3) homography from frame pixels to the plane.
    ties : (i, j) -> tie points between frames i and j, both in ``initial``.
    frame_sizes : frame -> (width, height) px.
    positions : frame -> (plane px of its centre, sigma px), for the frames with GPS.

    Returns
    -------
    frame -> refined (3, 3) homography, normalised so H[2, 2] = 1.
    """
    free = sorted(k for k in initial if k != root)
    if not free or not ties:
        return dict(initial)
    slot = {k: s for s, k in enumerate(free)}
    norms = {k: _normaliser(*frame_sizes[k]) for k in initial}
    # frame k's pixels -> plane is A_k (I + D_k) N_k, with A_k = initial_k N_k^-1 fixed: only D_k varies
    lift = {k: initial[k] @ np.linalg.inv(norms[k]) for k in initial}
    obs = [
        (i, j, _normalised_points(norms[i], t.points_i), _normalised_points(norms[j], t.points_j))
        for (i, j), t in ties.items()
        if i in initial and j in initial and len(t.points_i)
    ]
    # GPS observations, as one-sided "tie points" of the frame's centre against a fixed plane position
    centres = {
        k: _normalised_points(norms[k], np.array([[(w - 1) / 2, (h - 1) / 2]])) for k, (w, h) in frame_sizes.items()
    }
    anchored = [
        (k, centres[k], np.asarray(xy, np.float64), 1.0 / sigma)
        for k, (xy, sigma) in sorted((positions or {}).items())
        if k in slot
    ]
    perspective = np.array([8 * s + o for s in range(len(free)) for o in (6, 7)])
    rows, cols = _jacobian_structure(obs, slot, len(perspective), perspective, [k for k, *_ in anchored])
    shape = (rows.max() + 1, 8 * len(free))

    def correction(params: np.ndarray, k: int) -> np.ndarray:
        if k == root:
            return np.eye(3)
        return np.eye(3) + np.append(params[8 * slot[k] : 8 * slot[k] + 8], 0.0).reshape(3, 3)

    def residuals(params: np.ndarray) -> np.ndarray:
        parts = [
            _project(lift[i], correction(params, i), qi)[0] - _project(lift[j], correction(params, j), qj)[0]
            for i, j, qi, qj in obs
        ]
        gps = [weight * (_project(lift[k], correction(params, k), q)[0][0] - xy) for k, q, xy, weight in anchored]
        return np.concatenate([np.concatenate(parts).ravel(), *gps, perspective_damping * params[perspective]])

    def jacobian(params: np.ndarray) -> csr_matrix:
        data = []
        for i, j, qi, qj in obs:
            for k, q, sign in ((i, qi, 1.0), (j, qj, -1.0)):
                if k in slot:
                    data.append(sign * _projection_derivative(lift[k], correction(params, k), q).ravel())
        for k, q, _, weight in anchored:
            data.append(weight * _projection_derivative(lift[k], correction(params, k), q).ravel())
        data.append(np.full(len(perspective), perspective_damping))
        return csr_matrix((np.concatenate(data), (rows, cols)), shape=shape)

    x = _levenberg_marquardt(residuals, jacobian, np.zeros(8 * len(free)), loss_scale_px)
    refined = {k: initial[k] @ np.linalg.inv(norms[k]) @ correction(x, k) @ norms[k] for k in initial}
    return {k: H / H[2, 2] for k, H in refined.items()}


def _levenberg_marquardt(
    residuals: Callable[[np.ndarray], np.ndarray],
    jacobian: Callable[[np.ndarray], csr_matrix],
    x0: np.ndarray,
    f_scale: float,
    max_iterations: int = 100,
) -> np.ndarray:
    """Minimise ``sum rho(r_i^2 / f^2)`` with the soft-L1 ``rho(z) = 2 (sqrt(1 + z) - 1)`` by Levenberg-Marquardt
    on iteratively reweighted normal equations (Triggs et al. 2000, sec. 6; Marquardt's diagonal damping).

    The normal matrix has 8 rows per free frame, so it is formed densely from the sparse Jacobian and solved
    directly: a handful of iterations where an iterative trust-region solver needed hundreds of inner ones.
    """

    def cost(r: np.ndarray) -> float:
        return float(np.sum(2.0 * (np.sqrt(1.0 + (r / f_scale) ** 2) - 1.0)))

    x, r = x0.copy(), residuals(x0)
    current, lam = cost(r), 1e-3
    for _ in range(max_iterations):
        J = jacobian(x)
        w = 1.0 / np.sqrt(1.0 + (r / f_scale) ** 2)  # IRLS weight of soft-L1: rho'(z)
        JtW = J.T.multiply(w).tocsr()
        normal = (JtW @ J).toarray()
        gradient = JtW @ r
        diagonal = np.maximum(np.diag(normal), 1e-12)
        while True:
            step = np.linalg.solve(normal + lam * np.diag(diagonal), -gradient)
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


def _normalised_points(N: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(n, 3) homogeneous normalised coordinates ``N p`` of (n, 2) pixel points."""
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    return np.column_stack([pts, np.ones(len(pts))]) @ N.T


def _project(A: np.ndarray, C: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plane points (n, 2) of normalised points ``q`` (n, 3) through ``A C``, and their homogeneous (n, 3)."""
    h = q @ (A @ C).T
    return h[:, :2] / h[:, 2:3], h


# d(C q)/d(params): parameter m of D (row-major, D[2, 2] = 0) scales component ROW[m] of q by q[COL[m]]
_ROW = np.array([0, 0, 0, 1, 1, 1, 2, 2])
_COL = np.array([0, 1, 2, 0, 1, 2, 0, 1])


def _projection_derivative(A: np.ndarray, C: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(n, 2, 8) derivative of the plane points ``A C q`` (dehomogenised) by the 8 parameters of ``C = I + D``."""
    u, h = _project(A, C, q)
    dh = A[None, :, _ROW] * q[:, None, _COL]  # (n, 3, 8): A @ d(Cq)/dm
    return (dh[:, :2, :] - u[:, :, None] * dh[:, 2:3, :]) / h[:, 2, None, None]


def _jacobian_structure(
    obs: list[tuple[int, int, np.ndarray, np.ndarray]],
    slot: dict[int, int],
    n_damped: int,
    damped: np.ndarray,
    anchored: Sequence[int] = (),
) -> tuple[np.ndarray, np.ndarray]:
    """Row and column of every non-zero of the Jacobian, in the order ``jacobian`` lists their values: tie
    points, then the ``anchored`` frames' positions (2 rows each), then the damped parameters."""
    rows, cols = [], []
    r = 0
    block = np.arange(8)
    for i, j, qi, _ in obs:
        n = len(qi)
        for k in (i, j):
            if k in slot:
                point_rows = r + 2 * np.arange(n)[:, None, None] + np.arange(2)[None, :, None]  # (n, 2, 1)
                rows.append(np.broadcast_to(point_rows, (n, 2, 8)).ravel())
                cols.append(np.broadcast_to(8 * slot[k] + block, (n, 2, 8)).ravel())
        r += 2 * n
    for k in anchored:
        rows.append(np.repeat(r + np.arange(2), 8))
        cols.append(np.tile(8 * slot[k] + block, 2))
        r += 2
    rows.append(r + np.arange(n_damped))
    cols.append(damped)
    return np.concatenate(rows), np.concatenate(cols)


def _normaliser(width: int, height: int) -> np.ndarray:
    s = 2.0 / max(width, height)
    return np.array([[s, 0, -s * width / 2], [0, s, -s * height / 2], [0, 0, 1.0]])


def tie_residuals_px(homographies: dict[int, np.ndarray], ties: dict[Pair, TiePoints]) -> dict[Pair, np.ndarray]:
    """Per pair, (N,) distances in frame pixels between each tie point and its partner transferred
    through the plane (``H_j^-1 H_i``), averaged over both directions."""
    out: dict[Pair, np.ndarray] = {}
    for (i, j), t in ties.items():
        if i not in homographies or j not in homographies or not len(t.points_i):
            continue
        H_ij = np.linalg.inv(homographies[j]) @ homographies[i]
        d_j = np.linalg.norm(apply_homography(H_ij, t.points_i) - t.points_j, axis=1)
        d_i = np.linalg.norm(apply_homography(np.linalg.inv(H_ij), t.points_j) - t.points_i, axis=1)
        out[(i, j)] = 0.5 * (d_i + d_j)
    return out


def frame_corners(width: int, height: int) -> np.ndarray:
    """(4, 2) float64 pixel (x, y) of a frame's outer corners, clockwise from top-left, in OpenCV's
    convention (pixel centres at integers, so the frame spans -0.5 .. width - 0.5)."""
    return np.array([[0, 0], [width, 0], [width, height], [0, height]], dtype=np.float64) - 0.5


def is_plausible(H: np.ndarray, width: int, height: int, max_scale_ratio: float = 4.0) -> bool:
    """False for a frame homography that mirrors, folds or stretches the frame beyond reason.

    Corners run clockwise on screen (y down), so every turn of a sane footprint has a positive cross product.
    """
    c = apply_homography(H, frame_corners(width, height))
    edges = np.roll(c, -1, axis=0) - c
    cross = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    if not np.all(cross > 0):
        return False  # mirrored, or not a convex quadrilateral: the frame folded over
    lengths = np.linalg.norm(edges, axis=1) / np.array([width, height, width, height])
    return bool(lengths.max() / max(lengths.min(), 1e-9) < max_scale_ratio)
