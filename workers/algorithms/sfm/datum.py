"""The other control measurements of a flight and how they place a reconstruction in the world.

GPS fixes and DJI gimbal attitude (camera rotations from yaw / pitch / roll); the similarity that moves
a reconstruction onto control positions (GPS fixes or GCPs); and GCPs in a reconstruction
(triangulation, per-GCP report). GCP files themselves are read by ``gcp.py``.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, minimize_scalar

from workers.algorithms.geometry import Camera, rotation_from_vector, vector_from_rotation
from workers.algorithms.sfm.bundle import refine_points, triangulate_rays
from workers.algorithms.sfm.gcp import GroundControlPoint

# What a reconstruction's report names (core.labels has a display name for each, checked by a test):
# report["datum"], how the model was put in the world
DATUM_GPS_ATTITUDE = "gps_attitude"  # cameras seeded from GPS and attitude, settled on the fixes
DATUM_FIT = "similarity_to_gps_and_gcps"  # a 3D similarity to fixes and control points that spread in 3D
DATUM_LINE = "gps_line_level_cameras"  # fixes along a line: the line fitted, cameras taken as level
DATUM_NONE = "none"  # too little control: an arbitrary frame
DATUMS = (DATUM_GPS_ATTITUDE, DATUM_FIT, DATUM_LINE, DATUM_NONE)
IMAGE_STATUSES = ("registered", "placed again", "not registered")  # per image
GCP_ROLES = ("control", "tie", "checkpoint")  # per ground control point


# -- GPS fixes and DJI attitude -------------------------------------------------------------------------
@dataclass(frozen=True)
class GpsFix:
    """A camera-centre prior: ``position`` (E, N, Up) metres in the local frame, with its 1-sigma accuracy."""

    position: tuple[float, float, float]
    sigma_h: float = 5.0
    sigma_v: float = 10.0


@dataclass(frozen=True)
class Attitude:
    """DJI gimbal attitude in degrees, as in the XMP ``GimbalYawDegree`` etc.

    yaw : heading of the optical axis (of the image top when looking straight down), clockwise from north.
    pitch : elevation of the optical axis: 0 = horizontal, -90 = nadir.
    roll : about the optical axis, positive = the image's right side down (aviation sense).
    Camera to world = Rz(-yaw) Rx(pitch) Ry(roll) applied to a level camera looking north.

    That is the physical reading (a gimbal tilting down turns the image top forward). The Phantom 3
    frames of ``drone_brighton_strip1`` disagree: their ground moves up the image while the drone flies
    along its yaw, i.e. the image top faces yaw + 180; ``reconstruct`` notices such metadata (it does
    not fit the matches) and starts incrementally instead.
    """

    yaw: float
    pitch: float
    roll: float = 0.0


def rotation_from_attitude(attitude: Attitude) -> np.ndarray:
    """World (E, N, Up) -> camera rotation (3, 3) from DJI gimbal yaw / pitch / roll (see ``Attitude``)."""
    y, p, r = np.radians([attitude.yaw, attitude.pitch, attitude.roll])
    rz = np.array([[np.cos(-y), -np.sin(-y), 0.0], [np.sin(-y), np.cos(-y), 0.0], [0.0, 0.0, 1.0]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(p), -np.sin(p)], [0.0, np.sin(p), np.cos(p)]])
    ry = np.array([[np.cos(r), 0.0, np.sin(r)], [0.0, 1.0, 0.0], [-np.sin(r), 0.0, np.cos(r)]])
    # columns: camera x (right), y (down), z (forward) in the body frame (right, forward, up)
    level_north = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    return (rz @ rx @ ry @ level_north).T


# -- fitting a model to control positions ---------------------------------------------------------------
def similarity_3d(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares ``dst ~ s R src + t`` without reflection (Umeyama 1991); (N, 3) each, N >= 3."""
    if len(src) < 3 or src.shape != dst.shape:
        raise ValueError("similarity_3d needs at least 3 point pairs of equal shape")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    R = U @ d @ Vt
    s = float(np.trace(np.diag(S) @ d) / max((a**2).sum() / len(src), 1e-300))
    return s, R, mu_d - s * R @ mu_s


LEVEL_MIN = 0.2  # line_similarity: mean squared share of the x axes across the line that levelling needs


def line_similarity(src: np.ndarray, dst: np.ndarray, rotations: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity of camera centres ``src`` to collinear GPS fixes ``dst`` (N, 3), N >= 2.

    The line fixes scale and all of the rotation but the turn about the line. That turn is chosen so
    that the cameras are level (x axes horizontal: least squares over ``rotations`` (N, 3, 3), world ->
    camera), of the two level solutions the one whose ``y + z`` axes point down (cameras between looking
    ahead and looking straight down); the assumption OpenSfM makes for its "horizontal" / "vertical"
    orientation priors. When the x axes lie (nearly) along the line, levelling them hardly turns the model
    about it (mean squared share across the line under ``LEVEL_MIN``: photos whose right-hand side faces along
    the flight), and the turn that points the optical axes furthest down is taken instead (a survey's photos
    look down): levelled, a 2 x 4 nadir flight (9 m RMS across its line, a "line" for 5 m fixes) came out 20-25
    degrees off nadir.
    """
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    d_s, d_d = np.linalg.svd(a)[2][0], np.linalg.svd(b)[2][0]
    if (a @ d_s) @ (b @ d_d) < 0:
        d_s = -d_s
    scale = float(np.linalg.norm(b @ d_d)) / max(float(np.linalg.norm(a @ d_s)), 1e-300)
    axis = np.cross(d_s, d_d)
    angle = np.arctan2(np.linalg.norm(axis), d_s @ d_d)
    R0 = rotation_from_vector(axis / max(np.linalg.norm(axis), 1e-300) * angle)
    x_axes, yz_axes = rotations[:, 0, :] @ R0.T, (rotations[:, 1, :] + rotations[:, 2, :]) @ R0.T
    z_axes = rotations[:, 2, :] @ R0.T

    def tilt(theta: np.ndarray) -> np.ndarray:  # sum of squared heights of the turned x axes
        return np.sum(_turned_height(x_axes, d_d, np.atleast_1d(theta)) ** 2, axis=1)

    def height(theta: np.ndarray) -> np.ndarray:  # summed heights of the turned optical axes (down: negative)
        return _turned_height(z_axes, d_d, np.atleast_1d(theta)).sum(axis=1)

    theta = np.linspace(-np.pi, np.pi, 721)
    down = -_turned_height(yz_axes, d_d, theta).sum(axis=1)
    t = tilt(theta)
    across = x_axes - np.outer(x_axes @ d_d, d_d)
    if np.mean(np.sum(across**2, axis=1)) < LEVEL_MIN:  # the x axes along the line: levelling cannot choose
        start = float(theta[np.argmin(height(theta))])
        best = float(
            minimize_scalar(
                lambda a: float(height(a)[0]), bounds=(start - 0.01, start + 0.01), method="bounded",
                options={"xatol": 1e-10},
            ).x
        )  # fmt: skip
    else:
        first = int(np.argmin(t))
        far = np.abs(np.angle(np.exp(1j * (theta - theta[first])))) > np.pi / 2
        second = int(np.flatnonzero(far)[np.argmin(t[far])])
        start = theta[first] if down[first] >= down[second] else theta[second]
        best = float(
            minimize_scalar(
                lambda a: float(tilt(a)[0]),
                bounds=(start - 0.01, start + 0.01),
                method="bounded",
                options={"xatol": 1e-10},
            ).x
        )
    R = rotation_from_vector(d_d * best) @ R0
    return scale, R, mu_d - scale * R @ mu_s


def _turned_height(v: np.ndarray, d: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """(T, N) z of vectors v (N, 3) turned by each angle of ``theta`` (T,) about the unit axis d (Rodrigues)."""
    cos, sin = np.cos(theta)[:, None], np.sin(theta)[:, None]
    return v[:, 2] * cos + np.cross(d, v)[:, 2] * sin + d[2] * (v @ d) * (1.0 - cos)


def refine_similarity(
    src: np.ndarray, dst: np.ndarray, sigma: np.ndarray, s: float, R: np.ndarray, t: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """Weighted least-squares similarity ``dst ~ s R src + t``, started from ``(s, R, t)``.

    Parameters
    ----------
    src, dst : (N, 3) model and control positions; sigma : (N,) accuracy of each control, metres.
    Directions the controls leave free (e.g. the turn about a line) stay near the start.
    """
    x0 = np.concatenate([[np.log(s)], vector_from_rotation(R), t])

    def residuals(x: np.ndarray) -> np.ndarray:
        moved = np.exp(x[0]) * src @ rotation_from_vector(x[1:4]).T + x[4:]
        return ((moved - dst) / sigma[:, None]).ravel()

    x = least_squares(residuals, x0, method="trf", max_nfev=200).x
    return float(np.exp(x[0])), rotation_from_vector(x[1:4]), x[4:]


def control_layout(xyz: np.ndarray, sigma: float) -> str:
    """Control positions (N, 3) with accuracy ``sigma`` m: "spread" (they fix a 3D similarity), "line"
    (collinear within their noise) or "none" (too close together for their accuracy)."""
    if len(xyz) < 2:
        return "none"
    spread = np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False) / np.sqrt(len(xyz))
    if spread[0] < sigma:
        return "none"
    return "spread" if len(xyz) >= 3 and spread[1] >= max(2.0 * sigma, 0.05 * spread[0]) else "line"


# -- GCPs in a reconstruction ----------------------------------------------------------------------------
Observation = tuple[int, int, np.ndarray]  # (index into the GCP list, frame, (2,) pixel)


def observations_by_frame(gcps: Sequence[GroundControlPoint], names: Sequence[str]) -> list[Observation]:
    """Every GCP observation of an image in ``names`` (frame i is ``names[i]``); others are skipped."""
    frame_of = {name: f for f, name in enumerate(names)}
    return [
        (g, frame_of[name], np.asarray(xy, dtype=np.float64))
        for g, gcp in enumerate(gcps)
        for name, xy in gcp.observations.items()
        if name in frame_of
    ]


def triangulate_gcps(
    camera: Camera,
    rotations: np.ndarray,
    centres: np.ndarray,
    registered: np.ndarray,
    gcps: Sequence[GroundControlPoint],
    observations: list[Observation],
) -> dict[str, np.ndarray]:
    """GCP id -> (3,) position triangulated from its observations in registered frames (two or more).

    rotations, centres : (F, 3, 3), (F, 3) frame poses ``X_cam = R (X - C)``; registered : (F,) bool.
    """
    obs = [(k, f, p) for k, f, p in observations if registered[f]]
    if not obs:
        return {}
    group = np.array([k for k, _, _ in obs])
    frames = np.array([f for _, f, _ in obs])
    xy = np.array([p for _, _, p in obs])
    R, C = rotations[frames], centres[frames]
    d = np.einsum("kji,kj->ki", R, camera.unproject(xy))
    X, ok = triangulate_rays(C, d, group, len(gcps))
    X = refine_points(camera, R, C, xy, group, X)
    return {gcps[int(k)].id: X[k] for k in np.flatnonzero(ok)}


def report_gcps(
    gcps: Sequence[GroundControlPoint],
    observations: list[Observation],
    checkpoints: Collection[str],
    registered: np.ndarray,
    adjusted: Mapping[str, tuple[np.ndarray, np.ndarray]],
    triangulated: Mapping[str, np.ndarray],
    world: bool,
) -> tuple[dict, dict[str, np.ndarray]]:
    """Per GCP: role (control, tie, checkpoint), observations, RMS px of its adjusted observations, and
    metres from its known position (only in a world frame). Also GCP id -> its final position.

    adjusted : id -> (position (3,), residuals (n, 2) px) from the adjustment (controls and tie points).
    triangulated : id -> position from the final cameras (used for checkpoints).
    """
    report: dict[str, dict] = {}
    positions: dict[str, np.ndarray] = {}
    for g, gcp in enumerate(gcps):
        control, tie, checkpoint = GCP_ROLES
        role = checkpoint if gcp.id in checkpoints else control if gcp.position is not None else tie
        entry: dict = {"role": role, "observations": sum(1 for k, f, _ in observations if k == g and registered[f])}
        if role != "checkpoint" and gcp.id in adjusted:
            positions[gcp.id], res = adjusted[gcp.id]
            entry["rms_px"] = round(float(np.sqrt(np.mean(np.sum(res**2, axis=1)))), 6)
        elif gcp.id in triangulated:
            positions[gcp.id] = triangulated[gcp.id]
        if gcp.id in positions and gcp.position is not None and world:
            enu = positions[gcp.id] - gcp.position
            entry.update(
                residual_m=round(float(np.linalg.norm(enu)), 6), residual_enu_m=[round(float(v), 6) for v in enu]
            )
        report[gcp.id] = entry
    return report, positions


def checkpoint_rmse(report: Mapping[str, dict]) -> float | None:
    """RMS of the checkpoints' ``residual_m`` in a ``report_gcps`` report; None without any."""
    errors = [e["residual_m"] for e in report.values() if e["role"] == "checkpoint" and "residual_m" in e]
    return round(float(np.sqrt(np.mean(np.square(errors)))), 6) if errors else None
