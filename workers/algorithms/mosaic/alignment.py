"""Put every frame into one plane: a maximum spanning tree of pairwise homographies, then a global
least-squares adjustment of all frame homographies over all tie points (the homography variant of
bundle adjustment used by Brown & Lowe 2007 and OpenCV's ``detail::BundleAdjusterReproj``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

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
) -> dict[int, np.ndarray]:
    """Adjust all frame->plane homographies jointly so that every tie point pair meets in the plane.

    The root frame is held fixed (it defines the plane). Each other frame is parametrised by a
    correction ``I + D`` in its own normalised coordinates (centre 0, half-size 1), which keeps the
    eight unknowns per frame on the same scale. A soft-L1 loss down-weights residual outliers (Huber
    stalls at max_nfev here).

    The tie-point cost is nearly flat along one mode, the slow "bending" of a chain of frames through
    their perspective terms: on a synthetic strip the true solution costs more than one bent by 3 px,
    because sub-pixel keypoint biases are enough to choose the bend. ``perspective_damping`` ties each
    frame's perspective correction to the spanning-tree estimate (measured directly between overlapping
    frames): a correction of 1/damping in normalised units costs as much as a 1 px tie residual.

    Parameters
    ----------
    initial : frame -> (3, 3) homography from frame pixels to the plane.
    ties : (i, j) -> tie points between frames i and j, both in ``initial``.
    frame_sizes : frame -> (width, height) px.

    Returns
    -------
    frame -> refined (3, 3) homography, normalised so H[2, 2] = 1.
    """
    free = sorted(k for k in initial if k != root)
    if not free or not ties:
        return dict(initial)
    slot = {k: s for s, k in enumerate(free)}
    norms = {k: _normaliser(*frame_sizes[k]) for k in initial}
    obs = [(i, j, t) for (i, j), t in ties.items() if i in initial and j in initial and len(t.points_i)]

    def frame_h(params: np.ndarray, k: int) -> np.ndarray:
        if k == root:
            return initial[k]
        d = np.append(params[8 * slot[k] : 8 * slot[k] + 8], 0.0).reshape(3, 3)
        N = norms[k]
        return initial[k] @ np.linalg.inv(N) @ (np.eye(3) + d) @ N

    perspective = np.array([8 * s + o for s in range(len(free)) for o in (6, 7)])

    def residuals(params: np.ndarray) -> np.ndarray:
        parts = [
            apply_homography(frame_h(params, i), t.points_i) - apply_homography(frame_h(params, j), t.points_j)
            for i, j, t in obs
        ]
        return np.concatenate([np.concatenate(parts).ravel(), perspective_damping * params[perspective]])

    sparsity = _jacobian_sparsity(obs, slot, perspective)
    result = least_squares(
        residuals,
        np.zeros(8 * len(free)),
        jac_sparsity=sparsity,
        loss="soft_l1",
        f_scale=loss_scale_px,
        x_scale="jac",
        method="trf",
        max_nfev=200,
    )
    refined = {k: frame_h(result.x, k) for k in initial}
    return {k: H / H[2, 2] for k, H in refined.items()}


def _normaliser(width: int, height: int) -> np.ndarray:
    s = 2.0 / max(width, height)
    return np.array([[s, 0, -s * width / 2], [0, s, -s * height / 2], [0, 0, 1.0]])


def _jacobian_sparsity(obs: list[tuple[int, int, TiePoints]], slot: dict[int, int], damped: np.ndarray) -> lil_matrix:
    rows = sum(2 * len(t.points_i) for _, _, t in obs)
    sparsity = lil_matrix((rows + len(damped), 8 * len(slot)), dtype=np.int8)
    for k, column in enumerate(damped):
        sparsity[rows + k, column] = 1
    r = 0
    for i, j, t in obs:
        n = 2 * len(t.points_i)
        for k in (i, j):
            if k in slot:
                sparsity[r : r + n, 8 * slot[k] : 8 * slot[k] + 8] = 1
        r += n
    return sparsity


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
