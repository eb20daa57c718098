"""Measuring with a calibrated stereo rig: answered at once, from the rig JSON of a finished job.

Uses only NumPy (``workers.algorithms.calibration.stereo_rig``), so the API stays free of OpenCV.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from api.errors import ConflictError, InvalidInputError, NotFoundError
from api.models import MeasureRequest
from core.db import Database, Job
from core.kinds import JobKind, JobStatus
from core.settings import Settings
from workers.algorithms.calibration import StereoRig, measure
from workers.workspace import job_workspace


def load_rig(db: Database, settings: Settings, job_id: int) -> StereoRig:
    """The rig of stereo job ``job_id``; 404 unknown, 409 not calibrated (yet)."""
    with db.session() as s:
        job = s.get(Job, job_id)
        if job is None or job.kind != JobKind.stereo_calibration:
            raise NotFoundError(f"stereo rig {job_id} not found")
        status = job.status
    if status != JobStatus.succeeded:
        raise ConflictError(f"stereo rig {job_id} is {status}; measure once its calibration has succeeded")
    result = job_workspace(settings.data_dir, job_id).load_calibration()
    return StereoRig.from_json(result["rig"])


def measure_with_rig(db: Database, settings: Settings, job_id: int, body: MeasureRequest) -> dict[str, Any]:
    rig = load_rig(db, settings, job_id)
    if len(body.left) != len(body.right):
        raise InvalidInputError(f"{len(body.left)} left and {len(body.right)} right points; give them in pairs")
    left, right = np.array(body.left, dtype=np.float64), np.array(body.right, dtype=np.float64)
    for side, px, cam in (("left", left, rig.left), ("right", right, rig.right)):
        outside = np.flatnonzero((px < -0.5).any(axis=1) | (px[:, 0] > cam.width - 0.5) | (px[:, 1] > cam.height - 0.5))
        if len(outside):
            raise InvalidInputError(f"{side} point {int(outside[0])} lies outside the {cam.width}x{cam.height} photo")
    m = measure(rig, left, right, perturb_px=body.perturb_px)
    n = len(left)
    return {
        "units": "mm (board units), left camera frame: x right, y down, z forward",
        "perturb_px": body.perturb_px,
        "points": [
            {"xyz": m.points[i].tolist(), "sigma": float(m.point_sigma[i]), "ray_gap": float(m.ray_gap[i])}
            for i in range(n)
        ],
        "distances": [
            {"from": i, "to": j, "distance": float(m.distances[i, j]), "sigma": float(m.distance_sigma[i, j])}
            for i in range(n)
            for j in range(i + 1, n)
        ],
    }
