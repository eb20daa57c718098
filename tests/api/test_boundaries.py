"""The API process stays light: it enqueues stages by name and never loads OpenCV, CuPy or stage code."""

from __future__ import annotations

import subprocess
import sys


def test_the_api_never_imports_the_stage_code() -> None:
    probe = ("import sys; from api.main import create_app; from api.cli import build_parser; "
             "heavy = ['cv2', 'cupy', 'workers.stages', 'workers.algorithms', 'gpu_kernels.sift']; "
             "print([m for m in sys.modules if any(m == h or m.startswith(h + '.') for h in heavy)])")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
