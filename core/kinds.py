"""The job kinds and job statuses, one enum each for the API, the workers and the database.

Both are ``StrEnum``s: a member is the string it stands for, so JSON, the database and the viewer
(``web/kinds.js`` mirrors these names and values) see the same plain strings as before.
"""

from __future__ import annotations

import enum


class JobKind(enum.StrEnum):
    mosaic = "mosaic"
    calibration = "calibration"
    stereo_calibration = "stereo_calibration"
    crack_survey = "crack_survey"
    stereo_dem = "stereo_dem"


class JobStatus(enum.StrEnum):
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"

    @property
    def finished(self) -> bool:
        return self in (JobStatus.succeeded, JobStatus.failed, JobStatus.cancelled)
