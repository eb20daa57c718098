"""Bundle adjustment: camera poses, 3D points and (optionally) shared intrinsics adjusted together
so that every point projects onto its observations (Triggs et al., "Bundle adjustment - a modern
synthesis", 2000), with GPS priors on camera centres and position priors on control points.

Solved with ``scipy.optimize.least_squares`` ("trf", sparse finite-difference Jacobian from
``jac_sparsity``, ``x_scale="jac"``, a robust loss), as in SciPy's large-scale bundle adjustment
example. Parameters: per free frame a Rodrigues rotation vector and the camera centre (pose
``X_cam = R (X_world - C)``), per point its position, then the shared intrinsics that are refined
(focal in px with fy / fx held, k1, k2 of the ``distort_ideal`` Brown model).

Residuals, all in units of their standard deviation with image observations at 1 px:
reprojection ``projected - observed`` (px), GPS ``(C - gps) / sigma`` per axis, control points
``(X - known) / sigma``, and, without any prior, a gauge term that keeps the distance between two
camera centres (the other six gauge freedoms are removed by holding a frame fixed). The robust loss
applies to the reprojections of feature matches only; priors and protected observations (GCP clicks)
stay quadratic (a custom SciPy loss callable).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix

from workers.algorithms.geometry import Camera, apply_brown, rotations_from_vectors

LossName = Literal["linear", "huber", "soft_l1", "cauchy", "arctan"]
INTRINSICS = ("focal", "k1", "k2")
_GAUGE_WEIGHT = 1e4  # a 1e-4 relative change of the gauge baseline costs as much as a 1 px residual


@dataclass(frozen=True)
class BundleOptions:
    """How to adjust.

    loss, loss_scale_px : scipy robust loss and its ``f_scale`` (px; sigma units for priors). "soft_l1" by
        default: SciPy's "huber" and "cauchy" clip the Jacobian rows of residuals beyond ``f_scale`` to
        ~1e-8 and inflate their residuals accordingly, which stalls the lsmr trust-region solver (measured:
        100 iterations without converging where soft_l1 needs 10-30).
    outlier_threshold_px : after a first solve, drop observations whose reprojection error is above
        this and solve again (when more than 0.5 % are dropped); None solves once.
    refine_focal, refine_k1, refine_k2 : self-calibration of the shared intrinsics.
    max_nfev, ftol : per solve, passed to least_squares.
    """

    loss: LossName = "soft_l1"
    loss_scale_px: float = 1.0
    outlier_threshold_px: float | None = 4.0
    refine_focal: bool = False
    refine_k1: bool = False
    refine_k2: bool = False
    max_nfev: int = 100
    ftol: float = 1e-6

    def refined(self) -> tuple[str, ...]:
        flags = (self.refine_focal, self.refine_k1, self.refine_k2)
        return tuple(name for name, on in zip(INTRINSICS, flags, strict=True) if on)


def _empty_int() -> np.ndarray:
    return np.zeros(0, np.int64)


def _empty_xyz() -> np.ndarray:
    return np.zeros((0, 3))


@dataclass(frozen=True)
class BundleProblem:
    """Initial values and measurements; frames and points are rows, not frame ids.

    Attributes
    ----------
    camera : shared intrinsics, ``distort_ideal`` convention.
    rvecs, centres : (F, 3) float64 rotation vectors and camera centres (world).
    points : (P, 3) float64 world points.
    obs_frame, obs_point : (K,) int64 row of the observing frame and of the observed point.
    obs_xy : (K, 2) float64 observed pixel (x, y).
    gps_frame, gps_xyz, gps_sigma : (G,) frame rows with a GPS prior, (G, 3) positions, (G, 3) sigma m.
    prior_point, prior_xyz, prior_sigma : (Q,) point rows with a known position, (Q, 3), (Q,) sigma m.
    fixed_frames : (H,) frame rows whose pose is held.
    fixed_rotations : frame rows whose rotation (only) is held, e.g. to fix the roll about a line of GPS fixes.
    gauge_pair : two frame rows whose centre distance is held (for a problem without priors).
    protected : (K,) bool observations outside the robust loss and never rejected (GCP clicks), or None.
    focal_prior : (focal px, sigma px), e.g. from EXIF, when the focal length is refined: OpenSfM's
        ``exif_focal_sd``; keeps a weakly observed focal (forward motion, few views) from drifting.
    """

    camera: Camera
    rvecs: np.ndarray
    centres: np.ndarray
    points: np.ndarray
    obs_frame: np.ndarray
    obs_point: np.ndarray
    obs_xy: np.ndarray
    gps_frame: np.ndarray = field(default_factory=_empty_int)
    gps_xyz: np.ndarray = field(default_factory=_empty_xyz)
    gps_sigma: np.ndarray = field(default_factory=_empty_xyz)
    prior_point: np.ndarray = field(default_factory=_empty_int)
    prior_xyz: np.ndarray = field(default_factory=_empty_xyz)
    prior_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))
    fixed_frames: np.ndarray = field(default_factory=_empty_int)
    fixed_rotations: np.ndarray = field(default_factory=_empty_int)
    gauge_pair: tuple[int, int] | None = None
    protected: np.ndarray | None = None
    focal_prior: tuple[float, float] | None = None


@dataclass(frozen=True)
class BundleResult:
    """Adjusted values; ``residuals`` (K, 2) px (projected - observed) for every observation, rejected
    ones included; ``inlier`` (K,) bool the observations kept; ``point_valid`` (P,) bool points that
    kept enough observations (or a prior) to be adjusted."""

    rvecs: np.ndarray
    centres: np.ndarray
    points: np.ndarray
    camera: Camera
    residuals: np.ndarray
    inlier: np.ndarray
    point_valid: np.ndarray
    nfev: int
    cost: float


def reproject(
    camera: Camera,
    rvecs: np.ndarray,
    centres: np.ndarray,
    points: np.ndarray,
    obs_frame: np.ndarray,
    obs_point: np.ndarray,
) -> np.ndarray:
    """Pixels (K, 2) of ``points[obs_point]`` seen by frames ``obs_frame``; ``distort_ideal`` only.

    Vectorised twin of ``Camera.project(world_to_camera(...))``; points behind a camera project
    through ``|z|`` clipped to 1e-9 (they come out far off and are rejected as outliers).
    """
    if camera.convention != "distort_ideal":
        raise ValueError("bundle adjustment uses the distort_ideal convention; convert the camera first")
    R = rotations_from_vectors(rvecs)
    d = points[obs_point] - centres[obs_frame]
    xc = np.einsum("kij,kj->ki", R[obs_frame], d)
    z = xc[:, 2:3]
    z = np.where(np.abs(z) < 1e-9, 1e-9, z)
    distorted = apply_brown(xc[:, :2] / z, camera.k, camera.t)
    return distorted * [camera.fx, camera.fy] + [camera.cx, camera.cy]


class _Layout:
    """Where each unknown sits in the parameter vector: rotations, centres, points, intrinsics."""

    def __init__(self, problem: BundleProblem, point_free: np.ndarray, refined: tuple[str, ...]) -> None:
        n_frames = len(problem.rvecs)
        free_centre = np.ones(n_frames, bool)
        free_centre[problem.fixed_frames] = False
        free_rot = free_centre.copy()
        free_rot[problem.fixed_rotations] = False
        self.problem, self.refined = problem, refined
        self.free_rot, self.free_centre, self.point_free = free_rot, free_centre, point_free
        n_rot, n_centre = 3 * int(free_rot.sum()), 3 * int(free_centre.sum())
        self.rot_col = _columns(free_rot, 0)
        self.centre_col = _columns(free_centre, n_rot)
        self.point_col = _columns(point_free, n_rot + n_centre)
        self.intrinsic_col = n_rot + n_centre + 3 * int(point_free.sum())
        self.size = self.intrinsic_col + len(refined)

    def pack(self, rvecs: np.ndarray, centres: np.ndarray, points: np.ndarray, camera: Camera) -> np.ndarray:
        values = {"focal": camera.fx, "k1": camera.k1, "k2": camera.k2}
        return np.concatenate(
            [
                rvecs[self.free_rot].ravel(),
                centres[self.free_centre].ravel(),
                points[self.point_free].ravel(),
                [values[n] for n in self.refined],
            ]
        )

    def unpack(
        self, x: np.ndarray, base: tuple[np.ndarray, np.ndarray, np.ndarray, Camera]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, Camera]:
        rvecs, centres, points, camera = base[0].copy(), base[1].copy(), base[2].copy(), base[3]
        for target, free, col in (
            (rvecs, self.free_rot, self.rot_col),
            (centres, self.free_centre, self.centre_col),
            (points, self.point_free, self.point_col),
        ):
            if free.any():
                first = col[free][0]
                target[free] = x[first : first + 3 * int(free.sum())].reshape(-1, 3)
        changes = dict(zip(self.refined, x[self.intrinsic_col :].tolist(), strict=True))
        if "focal" in changes:
            f = changes.pop("focal")
            changes.update(fx=f, fy=f * camera.fy / camera.fx)
        return rvecs, centres, points, (camera.replace(**changes) if changes else camera)


def _columns(free: np.ndarray, offset: int) -> np.ndarray:
    """First parameter column of each row's 3-vector, -1 where the row is held."""
    return np.where(free, offset + 3 * (np.cumsum(free) - 1), -1)


def _residuals(layout: _Layout, x: np.ndarray, base: tuple, sel: np.ndarray) -> np.ndarray:
    p = layout.problem
    rvecs, centres, points, camera = layout.unpack(x, base)
    proj = reproject(camera, rvecs, centres, points, p.obs_frame[sel], p.obs_point[sel])
    parts = [
        (proj - p.obs_xy[sel]).ravel(),
        ((centres[p.gps_frame] - p.gps_xyz) / p.gps_sigma).ravel(),
        ((points[p.prior_point] - p.prior_xyz) / p.prior_sigma[:, None]).ravel(),
    ]
    if p.gauge_pair is not None:
        a, b = p.gauge_pair
        d0 = np.linalg.norm(base[1][a] - base[1][b])
        parts.append(np.array([_GAUGE_WEIGHT * (np.linalg.norm(centres[a] - centres[b]) - d0) / d0]))
    if p.focal_prior is not None and "focal" in layout.refined:
        parts.append(np.array([(camera.fx - p.focal_prior[0]) / p.focal_prior[1]]))
    return np.concatenate(parts)


def _sparsity(layout: _Layout, sel: np.ndarray) -> csr_matrix:
    """Which residual depends on which unknown: one block per observation, prior and gauge term."""
    p = layout.problem
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []

    def link(first_row: np.ndarray, n_rows: int, first_col: np.ndarray, n_cols: int = 3) -> None:
        ok = first_col >= 0
        r = first_row[ok, None, None] + np.arange(n_rows)[None, :, None]
        c = first_col[ok, None, None] + np.arange(n_cols)[None, None, :]
        r, c = np.broadcast_arrays(r, c)
        rows.append(r.ravel())
        cols.append(c.ravel())

    frame, point = p.obs_frame[sel], p.obs_point[sel]
    obs_rows = 2 * np.arange(len(frame))
    link(obs_rows, 2, layout.rot_col[frame])
    link(obs_rows, 2, layout.centre_col[frame])
    link(obs_rows, 2, layout.point_col[point])
    if layout.refined:
        link(obs_rows, 2, np.full(len(frame), layout.intrinsic_col), len(layout.refined))
    start = 2 * len(frame)
    link(start + 3 * np.arange(len(p.gps_frame)), 3, layout.centre_col[p.gps_frame])
    start += 3 * len(p.gps_frame)
    link(start + 3 * np.arange(len(p.prior_point)), 3, layout.point_col[p.prior_point])
    start += 3 * len(p.prior_point)
    if p.gauge_pair is not None:
        link(np.full(2, start), 1, layout.centre_col[list(p.gauge_pair)])
        start += 1
    if p.focal_prior is not None and "focal" in layout.refined:
        link(np.array([start]), 1, np.array([layout.intrinsic_col + layout.refined.index("focal")]), 1)
        start += 1
    r, c = np.concatenate(rows), np.concatenate(cols)
    return csr_matrix((np.ones(len(r), np.int8), (r, c)), shape=(start, layout.size))


def _solve(problem: BundleProblem, sel: np.ndarray, base: tuple, options: BundleOptions) -> tuple[tuple, int, float]:
    """Least-squares solves over the selected observations; returns (state, nfev, cost).

    SciPy rescales a robust loss's Jacobian by ``rho' + 2 rho'' f^2`` (Triggs' correction), which is 0
    for Huber and Cauchy residuals beyond ``f_scale``: started far from the solution, every residual
    is there and the solver stalls. So the loss scale starts at 3x the residuals' robust sigma
    (median absolute deviation) and is brought down by quarters to ``loss_scale_px``.
    """
    counts = np.bincount(problem.obs_point[sel], minlength=len(problem.points))
    has_prior = np.zeros(len(problem.points), bool)
    has_prior[problem.prior_point] = True
    layout = _Layout(problem, (counts >= 2) | (has_prior & (counts >= 1)), options.refined())
    if layout.size == 0:
        return base, 0, 0.0
    sparsity = _sparsity(layout, sel)
    nfev, cost, state = 0, 0.0, base
    for scale in _loss_scales(problem, sel, base, options):
        x0 = layout.pack(*state)
        result = least_squares(
            lambda x, s=state: _residuals(layout, x, s, sel),
            x0,
            jac_sparsity=sparsity,
            method="trf",
            x_scale="jac",
            loss=_mixed_loss(options.loss, _robust_rows(problem, sel)),
            f_scale=scale,
            max_nfev=options.max_nfev,
            ftol=options.ftol,
            xtol=1e-10,
            tr_solver="lsmr",
        )
        state = layout.unpack(result.x, state)
        nfev, cost = nfev + int(result.nfev), float(result.cost)
    return state, nfev, cost


def _robust_rows(problem: BundleProblem, sel: np.ndarray) -> np.ndarray:
    """(R,) bool over the residual rows of ``_residuals`` that get the robust loss: the reprojections of
    unprotected observations (feature matches), not protected ones (GCP clicks) nor priors."""
    robust = np.ones(len(problem.obs_frame), bool) if problem.protected is None else ~problem.protected
    return np.repeat(robust[sel], 2)


def _mixed_loss(kind: str, robust: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """A SciPy loss callable: ``kind`` on the ``robust`` leading residual rows, plain squares elsewhere, so
    that priors and GCP observations keep the weight their sigma gives them however far they are pulled."""

    def rho(z: np.ndarray) -> np.ndarray:
        out = np.stack([z, np.ones_like(z), np.zeros_like(z)])
        rows = np.flatnonzero(robust)
        out[:, rows] = robust_rho(kind, z[rows])
        return out

    return rho


def robust_rho(kind: str, z: np.ndarray) -> np.ndarray:
    """(3, N) rho(z), rho'(z), rho''(z) of SciPy's named losses, z = (r / f_scale)^2."""
    if kind == "linear":
        return np.stack([z, np.ones_like(z), np.zeros_like(z)])
    if kind == "soft_l1":
        t = 1.0 + z
        return np.stack([2.0 * (np.sqrt(t) - 1.0), t**-0.5, -0.5 * t**-1.5])
    if kind == "huber":
        big = z > 1.0
        root = np.sqrt(np.where(big, z, 1.0))
        return np.stack(
            [np.where(big, 2.0 * root - 1.0, z), np.where(big, 1.0 / root, 1.0), np.where(big, -0.5 / root**3, 0.0)]
        )
    if kind == "cauchy":
        return np.stack([np.log1p(z), 1.0 / (1.0 + z), -1.0 / (1.0 + z) ** 2])
    if kind == "arctan":
        return np.stack([np.arctan(z), 1.0 / (1.0 + z**2), -2.0 * z / (1.0 + z**2) ** 2])
    raise ValueError(f"unknown loss {kind!r}; expected one of linear, soft_l1, huber, cauchy, arctan")


def _loss_scales(problem: BundleProblem, sel: np.ndarray, base: tuple, options: BundleOptions) -> list[float]:
    final = options.loss_scale_px
    if options.loss == "linear" or not sel.any():
        return [final]
    r = reproject(base[3], base[0], base[1], base[2], problem.obs_frame[sel], problem.obs_point[sel])
    start = 3.0 * 1.4826 * float(np.median(np.abs(r - problem.obs_xy[sel])))
    scales = []
    while start > 2.0 * final:
        scales.append(start)
        start /= 4.0
    return [*scales, final]


def adjust(problem: BundleProblem, options: BundleOptions = BundleOptions()) -> BundleResult:
    """Bundle-adjust ``problem``, rejecting outlier observations between two solves.

    Returns
    -------
    BundleResult. A problem with no observations comes back unchanged.
    """
    _check(problem)
    base = (
        problem.rvecs.astype(np.float64),
        problem.centres.astype(np.float64),
        problem.points.astype(np.float64),
        problem.camera,
    )
    inlier = np.ones(len(problem.obs_frame), bool)
    state, nfev, cost = _solve(problem, inlier, base, options)
    if options.outlier_threshold_px is not None and len(inlier):
        error = np.linalg.norm(reproject(*_project_args(problem, state)) - problem.obs_xy, axis=1)
        inlier = error <= options.outlier_threshold_px
        if problem.protected is not None:
            inlier |= problem.protected
        if (~inlier).sum() > 0.005 * len(inlier):  # a handful rejected: the robust first solve stands
            state, more, cost = _solve(problem, inlier, state, options)
            nfev += more
    residuals = reproject(*_project_args(problem, state)) - problem.obs_xy
    counts = np.bincount(problem.obs_point[inlier], minlength=len(problem.points))
    valid = counts >= 2
    valid[problem.prior_point[counts[problem.prior_point] >= 1]] = True
    rvecs, centres, points, camera = state
    return BundleResult(rvecs, centres, points, camera, residuals, inlier, valid, nfev, cost)


def _project_args(problem: BundleProblem, state: tuple) -> tuple:
    rvecs, centres, points, camera = state
    return camera, rvecs, centres, points, problem.obs_frame, problem.obs_point


def _check(problem: BundleProblem) -> None:
    k = len(problem.obs_frame)
    if len(problem.obs_point) != k or problem.obs_xy.shape != (k, 2):
        raise ValueError("obs_frame, obs_point and obs_xy must describe the same K observations")
    if problem.rvecs.shape != problem.centres.shape or problem.rvecs.shape[1:] != (3,):
        raise ValueError("rvecs and centres must both be (F, 3)")
    if k and (problem.obs_frame.max() >= len(problem.rvecs) or problem.obs_point.max() >= len(problem.points)):
        raise ValueError("an observation refers to a frame or point row that does not exist")
    if np.any(problem.gps_sigma <= 0) or np.any(problem.prior_sigma <= 0):
        raise ValueError("prior sigmas must be positive")
    if problem.camera.convention != "distort_ideal":
        raise ValueError("bundle adjustment uses the distort_ideal convention; convert the camera first")


def rms(residuals: np.ndarray) -> float:
    """Root mean square length of (K, 2) residual vectors, px; NaN when K = 0."""
    return float(np.sqrt(np.mean(np.sum(residuals**2, axis=1)))) if len(residuals) else float("nan")


def rms_by_group(residuals: np.ndarray, group: np.ndarray) -> dict[int, tuple[float, int]]:
    """Per group id (e.g. frame): (RMS residual length px, observation count)."""
    sq = np.sum(residuals**2, axis=1)
    out: dict[int, tuple[float, int]] = {}
    for g in np.unique(group):
        sel = group == g
        out[int(g)] = (float(np.sqrt(sq[sel].mean())), int(sel.sum()))
    return out


def triangulate_rays(
    centres: np.ndarray, directions: np.ndarray, group: np.ndarray, n_groups: int
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares intersection of groups of rays: the point closest to all rays of a group (the
    multi-view midpoint, Hartley & Zisserman 12.5 / Szeliski 11.2.1).

    Parameters
    ----------
    centres : (K, 3) float64 ray origins (camera centres), world.
    directions : (K, 3) float64 unit ray directions, world.
    group : (K,) int64 group (track) of each ray, 0 .. n_groups - 1.

    Returns
    -------
    points : (n_groups, 3) float64; NaN where unsolved.
    ok : (n_groups,) bool, False for groups with fewer than two rays or (near-)parallel rays.
    """
    A = np.eye(3)[None] - directions[:, :, None] * directions[:, None, :]
    b = np.einsum("kij,kj->ki", A, centres)
    A_sum = _group_sum(A.reshape(-1, 9), group, n_groups).reshape(-1, 3, 3)
    b_sum = _group_sum(b, group, n_groups)
    counts = np.bincount(group, minlength=n_groups)
    # the smallest eigenvalue is sin^2 of the rays' spread; 1e-8 ~ 0.006 degrees
    ok = (counts >= 2) & (np.linalg.eigvalsh(A_sum)[:, 0] > 1e-8 * np.maximum(counts, 1))
    points = np.full((n_groups, 3), np.nan)
    if ok.any():
        points[ok] = np.linalg.solve(A_sum[ok], b_sum[ok][:, :, None])[:, :, 0]
    return points, ok


def refine_points(
    camera: Camera,
    rotations: np.ndarray,
    centres: np.ndarray,
    xy: np.ndarray,
    group: np.ndarray,
    points: np.ndarray,
    iterations: int = 5,
) -> np.ndarray:
    """Gauss-Newton on each point's reprojection error with the cameras held (structure-only BA).

    Parameters
    ----------
    rotations, centres : (K, 3, 3) and (K, 3) pose of the camera of each observation.
    xy : (K, 2) observed pixels; group : (K,) point row of each observation.
    points : (G, 3) initial points; rows with fewer than two observations are returned unchanged.

    Returns
    -------
    (G, 3) refined points.
    """
    X = points.copy()
    n = len(X)
    live = (np.bincount(group, minlength=n) >= 2) & np.all(np.isfinite(X), axis=1)
    use = live[group]
    R, C, obs, grp = rotations[use], centres[use], xy[use], group[use]
    for _ in range(iterations if use.any() else 0):
        cam = np.einsum("kij,kj->ki", R, X[grp] - C)
        cam[:, 2] = np.maximum(cam[:, 2], 1e-9)  # behind a camera: left for the caller to reject
        r = camera.project(cam) - obs
        J = camera.project_jacobian(cam) @ R
        H = _group_sum(np.einsum("kai,kaj->kij", J, J).reshape(-1, 9), grp, n).reshape(-1, 3, 3)
        g = _group_sum(np.einsum("kai,ka->ki", J, r), grp, n)
        trace = np.maximum(np.trace(H, axis1=1, axis2=2), 1e-300)
        H[live] += 1e-9 * trace[live, None, None] * np.eye(3)
        ok = live & (np.linalg.det(H / trace[:, None, None]) > 1e-15)  # scale-free: not (near-)singular
        if not ok.any():
            break
        X[ok] -= np.linalg.solve(H[ok], g[ok][:, :, None])[:, :, 0]
    return X


def _group_sum(values: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """(K, D) -> (n, D) sums of the rows of each group."""
    sums = [np.bincount(group, weights=values[:, d], minlength=n) for d in range(values.shape[1])]
    return np.stack(sums, axis=1).astype(np.float64)
