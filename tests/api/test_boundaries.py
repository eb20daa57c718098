"""The API process stays light: it enqueues stages by name and never loads OpenCV, CuPy, SciPy or stage code.

The exceptions are NumPy-only geometry (the camera model and stereo triangulation), which the API uses
to answer a measurement with a calibrated rig at once instead of queueing a job for milliseconds of
arithmetic, and the GCP and mesh parsers (NumPy and pyproj), which check an upload before it is stored.
"""

from __future__ import annotations

import subprocess
import sys

NUMPY_ONLY = ["workers.algorithms", "workers.algorithms.camera", "workers.algorithms.stereo",
              "workers.algorithms.gcp", "workers.algorithms.georef", "workers.algorithms.mesh"]


def test_the_api_never_imports_the_stage_code() -> None:
    probe = ("import sys; from api.main import create_app; from api.cli import build_parser; "
             "heavy = ['cv2', 'cupy', 'scipy', 'workers.stages', 'workers.algorithms', 'gpu_kernels.sift']; "
             f"allowed = {NUMPY_ONLY!r}; "
             "print([m for m in sys.modules if m not in allowed and any(m == h or m.startswith(h + '.') "
             "for h in heavy)])")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
