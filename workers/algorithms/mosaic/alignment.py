"""Put every frame into one plane: a maximum spanning tree of pairwise homographies, then a global
least-squares adjustment of all frame homographies over all tie points (the homography variant of
bundle adjustment used by Brown & Lowe 2007 and OpenCV's ``detail::BundleAdjusterReproj``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workers.algorithms.mosaic.plane_adjustment import (
    PARAMETER_COL,
    PARAMETER_ROW,
    PlaneProblem,
    inverse_diagonal_blocks,
    levenberg_marquardt,
    point_derivative,
)

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
    root: int | None,
    frame_sizes: dict[int, tuple[int, int]],
    loss_scale_px: float = 2.0,
    perspective_damping: float = 1000.0,
    positions: dict[int, tuple[np.ndarray, float]] | None = None,
    shape_weight: float = 0.0,
) -> dict[int, np.ndarray]:
    """Adjust all frame->plane homographies jointly so that every tie point pair meets in the plane.

    The root frame is held fixed (it defines the plane). Each other frame is parametrised by a
    correction ``I + D`` in its own normalised coordinates (centre 0, half-size 1), which keeps the
    eight unknowns per frame on the same scale. A tie point's miss is where its two frames put it in the
    plane, counted in the photos' pixels (divided by the frames' scale: see :class:`PlaneProblem`'s
    ``unit_px``), so that frames cannot shrink their points' noise away. A soft-L1 loss down-weights
    residual outliers. The derivatives are analytic and the normal equations (8 unknowns per frame) are
    solved directly by Levenberg-Marquardt: 1.4 s for 30 frames and 40k tie points, where scipy's
    ``least_squares`` with finite differences over a sparsity pattern took 167 s and stopped at its
    evaluation limit.

    The tie-point cost is nearly flat along one mode, the slow "bending" of a chain of frames through
    their perspective terms: on a synthetic strip the true solution costs more than one bent by 3 px,
    because sub-pixel keypoint biases are enough to choose the bend. ``perspective_damping`` ties each
    frame's perspective correction to the spanning-tree estimate (measured directly between overlapping
    frames): a correction of 1/damping in normalised units costs as much as a 1 px tie residual.

    ``positions`` holds what GPS says about a frame: where its centre lies in the plane and how sure that
    is, ``(xy (2,) plane px, sigma px)``. Each is one more observation, its miss divided by sigma, so a
    long strip cannot bend further than its GPS allows (tie points alone constrain a chain's shape only
    locally). The root frame is fixed: its position only matters through the plane's placement. With
    ``root`` None no frame is: the fixes must then place the plane and ``shape_weight`` shape it.

    ``shape_weight`` adds a prior on each free frame's shape: the aspect ``(a - d) / (a + d)`` and shear
    ``(b + c) / (a + d)`` of its map's Jacobian ``[[a, b], [c, d]]`` at its centre are zero (square pixels, as a
    near-nadir camera's), each times ``shape_weight`` one more residual (so 1 / shape_weight of aspect costs as
    much as a 1 px tie residual).

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
    built = _plane_problem(initial, ties, root, frame_sizes, perspective_damping, positions, shape_weight)
    if built is None:
        return dict(initial)
    problem, frames, norms = built
    number = {k: f for f, k in enumerate(frames)}
    free = [k for k in frames if k != root]
    x = levenberg_marquardt(problem.residuals, problem.normal_equations, np.zeros(8 * len(free)), loss_scale_px)
    C = problem.corrections(x)
    refined = {k: initial[k] @ np.linalg.inv(norms[k]) @ C[number[k]] @ norms[k] for k in initial}
    return {k: H / H[2, 2] for k, H in refined.items()}


def _plane_problem(
    initial: dict[int, np.ndarray],
    ties: dict[Pair, TiePoints],
    root: int | None,
    frame_sizes: dict[int, tuple[int, int]],
    perspective_damping: float,
    positions: dict[int, tuple[np.ndarray, float]] | None,
    shape_weight: float,
) -> tuple[PlaneProblem, list[int], dict[int, np.ndarray]] | None:
    """:func:`refine_homographies`' observations as a :class:`PlaneProblem` at ``initial`` (parameters zero),
    with the frames in problem order and their normalisers; None with no free frame or no tie point."""
    free = sorted(k for k in initial if k != root)
    obs = [(i, j, t) for (i, j), t in ties.items() if i in initial and j in initial and len(t.points_i)]
    if not free or not obs:
        return None
    frames = sorted(initial)  # numbered 0..F-1 in the problem
    number = {k: f for f, k in enumerate(frames)}
    slot = np.array([free.index(k) if k != root else -1 for k in frames], np.int64)
    norms = {k: _normaliser(*frame_sizes[k]) for k in initial}
    # frame k's pixels -> plane is A_k (I + D_k) N_k, with A_k = initial_k N_k^-1 fixed: only D_k varies
    lift = np.stack([initial[k] @ np.linalg.inv(norms[k]) for k in frames])
    counts = np.array([len(t.points_i) for _, _, t in obs])
    # GPS observations: each frame's centre against a fixed plane position, weighted by 1 / sigma
    gps = [(k, np.asarray(xy, np.float64), 1.0 / sigma) for k, (xy, sigma) in sorted((positions or {}).items())]
    gps = [g for g in gps if g[0] in initial and g[0] != root]
    centre = [_normalised_points(norms[k], np.array([[(frame_sizes[k][0] - 1) / 2, (frame_sizes[k][1] - 1) / 2]]))
              for k, _, _ in gps]  # fmt: skip
    problem = PlaneProblem(
        lift=lift,
        slot=slot,
        q_i=np.concatenate([_normalised_points(norms[i], t.points_i) for i, _, t in obs]),
        q_j=np.concatenate([_normalised_points(norms[j], t.points_j) for _, j, t in obs]),
        f_i=np.repeat([number[i] for i, _, _ in obs], counts),
        f_j=np.repeat([number[j] for _, j, _ in obs], counts),
        starts=np.concatenate([[0], np.cumsum(counts)[:-1]]),
        q_gps=np.concatenate(centre) if gps else np.zeros((0, 3)),
        f_gps=np.array([number[k] for k, _, _ in gps], np.int64),
        xy_gps=np.array([xy for _, xy, _ in gps], np.float64).reshape(-1, 2),
        w_gps=np.array([w for _, _, w in gps], np.float64),
        unit_px=np.array([1.0 / norms[k][0, 0] for k in frames]),  # frame px per normalised unit
        perspective_damping=perspective_damping,
        shape_weight=shape_weight,
    )
    return problem, frames, norms


def corner_sigmas(
    homographies: dict[int, np.ndarray],
    ties: dict[Pair, TiePoints],
    frame_sizes: dict[int, tuple[int, int]],
    positions: dict[int, tuple[np.ndarray, float]],
    shape_weight: float,
    loss_scale_px: float = 2.0,
) -> dict[int, float]:
    """Frame -> the standard error (1 sigma, plane px) of its least well known corner: the precision a bundle
    adjustment propagates (Förstner & Wrobel 2016, ch. 4), from :func:`refine_homographies`' normal equations at
    its solution ``homographies`` with the same observations (tie points, ``positions``, the square-pixel prior
    ``shape_weight``), scaled by their a posteriori variance of unit weight (so by the tie points' scatter as
    found, not as assumed). A corner's error is its 2 x 2 covariance's trace, as an RMS distance.

    No frame is held: the fixes are the datum, with :func:`level_plane`'s condition held exactly, as the adjustment
    holds it (its last round keeps the levelled root): the frames' perspective rows average to zero. Along a
    straight strip the fixes and the prior tell that tilt only weakly (the unit test's strip: 7.4 px without the
    condition, 2.0 with it), so a flight whose attitude does not average out is off by more than this says.

    Only the frames tie points join to the largest group of frames are given one (a frame whose neighbours were
    rejected is left out); empty without GPS positions, or when the normal equations are singular or not
    finite.
    """
    joined = _largest_group(homographies, ties)
    kept = {k: homographies[k] for k in joined}
    fixes = {k: p for k, p in positions.items() if k in joined}
    built = _plane_problem(kept, ties, None, frame_sizes, 0.0, fixes, shape_weight) if fixes else None
    if built is None:
        return {}
    problem, frames, norms = built
    zero = np.zeros(8 * len(frames))
    normal, _ = problem.normal_equations(zero, loss_scale_px)
    datum = _mean_perspective(problem.lift)
    try:
        blocks = inverse_diagonal_blocks(normal, datum)  # (F, 8, 8), in frame order
    except np.linalg.LinAlgError:
        return {}
    corners = np.concatenate([_normalised_points(norms[k], frame_corners(*frame_sizes[k])) for k in frames])
    J = point_derivative(np.repeat(problem.lift, 4, axis=0), corners)  # (4F, 2, 8)
    covariance = J @ np.repeat(blocks, 4, axis=0) @ J.transpose(0, 2, 1)
    factor = problem.variance_factor(zero, loss_scale_px, conditions=len(datum))
    worst = (factor * np.trace(covariance, axis1=1, axis2=2)).reshape(-1, 4).max(axis=1)
    if not np.all(np.isfinite(worst)) or np.any(worst < 0):
        return {}
    return {k: float(np.sqrt(v)) for k, v in zip(frames, worst, strict=True)}


def _largest_group(homographies: dict[int, np.ndarray], ties: dict[Pair, TiePoints]) -> set[int]:
    """The largest set of frames of ``homographies`` that tie points join (union-find over the pairs)."""
    parent = {k: k for k in homographies}

    def find(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for (i, j), t in ties.items():
        if i in parent and j in parent and len(t.points_i):
            parent[find(i)] = find(j)
    groups: dict[int, set[int]] = {}
    for k in homographies:
        groups.setdefault(find(k), set()).add(k)
    return max(groups.values(), key=len, default=set())


def _mean_perspective(lift: np.ndarray) -> np.ndarray:
    """(2, 8F) the derivative of the frames' summed perspective rows ``M[2, :2] / M[2, 2]`` (normalised
    coordinates, :func:`level_plane`'s) by the parameters of ``M = A (I + D)`` at ``D = 0``: parameter m of D
    adds ``A[2, ROW[m]]`` to ``M[2, COL[m]]``."""
    row, col = PARAMETER_ROW, PARAMETER_COL
    gain = lift[:, 2, row]  # (F, 8): what parameter m adds to M[2, COL[m]]
    out = np.zeros((2, len(lift), 8))
    for j in (0, 1):
        p = lift[:, 2, j] / lift[:, 2, 2]
        out[j] = (gain * (col == j) - p[:, None] * gain * (col == 2)) / lift[:, 2, 2, None]
    return out.reshape(2, -1)


LEVEL_ITERATIONS = 8  # Newton steps of the levelling: quadratic convergence, 3-4 reach 1e-12 on strips


def level_plane(homographies: dict[int, np.ndarray], frame_sizes: dict[int, tuple[int, int]]) -> dict[int, np.ndarray]:
    """The frames moved by one plane homography so that, on average, they have square pixels and no tilt.

    The adjustment holds the root frame fixed, so the plane is the root's image plane: tilted against the
    ground by the root's own attitude. Tie points cannot tell, and on a long strip that tilt is a fan (the
    mosaic wider at one end: 20-35 px at the corners of a 12-frame 20000-px strip after one similarity).
    A homography of the plane has eight parameters; a similarity (four) changes nothing a map cares
    about, the other four (aspect, shear, two perspective terms) are fixed here by what a survey camera
    gives: square pixels and an attitude that averages out over a flight. Each frame's aspect
    ``(a - d) / (a + d)`` and shear ``(b + c) / (a + d)`` of its Jacobian ``[[a, b], [c, d]]`` at its centre,
    and its perspective row in its own normalised coordinates (centre 0, half-size 1), average to zero over
    the frames.

    Parameters
    ----------
    homographies : frame -> (3, 3) frame px -> plane px.
    frame_sizes : frame -> (width, height) px.

    Returns
    -------
    frame -> (3, 3) homography onto the levelled plane, normalised so H[2, 2] = 1; the plane's scale and
    place are kept near the frames' (the plane point under their mean centre does not move).
    """
    if len(homographies) < 2:
        return dict(homographies)
    keys = sorted(homographies)
    centres = np.array([apply_homography(homographies[k], _centre(frame_sizes[k]))[0] for k in keys])
    local = np.stack([homographies[k] @ np.linalg.inv(_normaliser(*frame_sizes[k])) for k in keys])
    scale = float(np.mean(np.sqrt(np.abs(np.linalg.det(local[:, :2, :2] / local[:, 2:, 2:])))))
    # plane units about the frames' mean centre, one frame's half-size per unit: every parameter O(1)
    to_unit = np.array([[1 / scale, 0, 0], [0, 1 / scale, 0], [0, 0, 1]]) @ _translation(-centres.mean(axis=0))
    M = to_unit @ local

    def statistics(params: np.ndarray) -> np.ndarray:
        N = _gauge(params) @ M
        N = N / N[:, 2:, 2:]
        # the frame's local affine at its centre (the Jacobian there), and its perspective row
        J = N[:, :2, :2] - N[:, :2, 2:] @ N[:, 2:, :2]
        trace = J[:, 0, 0] + J[:, 1, 1]
        per_frame = [(J[:, 0, 0] - J[:, 1, 1]) / trace, (J[:, 0, 1] + J[:, 1, 0]) / trace, N[:, 2, 0], N[:, 2, 1]]
        return np.mean(per_frame, axis=1)

    params = np.zeros(4)
    for _ in range(LEVEL_ITERATIONS):
        value = statistics(params)
        if np.abs(value).max() < 1e-13:
            break
        step = 1e-7
        jacobian = np.column_stack([(statistics(params + step * e) - value) / step for e in np.eye(4)])
        params = params - np.linalg.solve(jacobian, value)
    G = np.linalg.inv(to_unit) @ _gauge(params) @ to_unit
    levelled = {k: G @ homographies[k] for k in keys}
    return {k: H / H[2, 2] for k, H in levelled.items()}


def _gauge(params: np.ndarray) -> np.ndarray:
    """(3, 3) the plane homography of (aspect, shear, perspective x, perspective y): what a similarity
    leaves of a homography."""
    aspect, shear, gx, gy = params
    return np.array([[1 + aspect, shear, 0.0], [shear, 1 - aspect, 0.0], [gx, gy, 1.0]])


def _centre(size: tuple[int, int]) -> np.ndarray:
    return np.array([[(size[0] - 1) / 2, (size[1] - 1) / 2]])


def _translation(offset: np.ndarray) -> np.ndarray:
    return np.array([[1.0, 0, offset[0]], [0, 1.0, offset[1]], [0, 0, 1]])


def _normalised_points(N: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(n, 3) homogeneous normalised coordinates ``N p`` of (n, 2) pixel points."""
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    return np.column_stack([pts, np.ones(len(pts))]) @ N.T


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


def triple_overlap_share(
    homographies: dict[int, np.ndarray], frame_sizes: dict[int, tuple[int, int]], min_share: float = 0.08
) -> float:
    """Share of the frames, each with both neighbours in flight order (frame number), whose neighbours overlap
    each other by at least ``min_share`` of the frame's own area on the plane: ground three frames see. A
    strip carries its scale from frame to frame only through such ground; at 50 % forward overlap or less the
    neighbours at most touch, and each frame's scale along the strip is free (1.0 when there is no such frame).
    8 %: 54 % forward overlap gives it; the slivers that headings jittered by 0.3 degrees leave at 50 % reach 5 %
    (on a 305-frame strip 42 % of the frames had 2 %, 1 % had 5 %), and carried no scale there."""
    import cv2  # the module's other functions need no OpenCV

    keys = sorted(homographies)
    quads = {k: apply_homography(homographies[k], frame_corners(*frame_sizes[k])).astype(np.float32) for k in keys}
    shares = []
    for before, frame, after in zip(keys, keys[1:], keys[2:], strict=False):
        common, _ = cv2.intersectConvexConvex(quads[before], quads[after])
        shares.append(common >= min_share * abs(cv2.contourArea(quads[frame])))
    return float(np.mean(shares)) if shares else 1.0
