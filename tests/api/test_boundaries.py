"""The API process stays light: it enqueues stages by name and never loads OpenCV, CuPy, SciPy or stage code.

The exceptions are NumPy-only geometry (the camera model and stereo triangulation), which the API uses
to answer a measurement with a calibrated rig at once instead of queueing a job for milliseconds of
arithmetic, the GCP and mesh parsers (NumPy and pyproj), which check an upload before it is stored, and the
counts a calibration needs (``calibration.limits``, no imports).

And the packages depend one way: ``api`` and ``workers`` both on ``core`` (settings, job records, kinds),
``api`` on ``workers``, never ``workers`` on ``api`` nor ``core`` on either.
"""

from __future__ import annotations

import ast
import subprocess
import sys

# The algorithm packages load their modules lazily: importing one of these loads only what the API names.
NUMPY_ONLY = [
    "workers.algorithms",
    "workers.algorithms.geometry",
    "workers.algorithms.geometry.camera",
    "workers.algorithms.geometry.rotation",
    "workers.algorithms.geometry.geodesy",
    "workers.algorithms.calibration",
    "workers.algorithms.calibration.limits",
    "workers.algorithms.calibration.stereo_rig",
    "workers.algorithms.sfm",
    "workers.algorithms.sfm.gcp",
    "workers.algorithms.specimen",
    "workers.algorithms.specimen.mesh",
]


def loaded_after(imports: str, packages: list[str]) -> list[str]:
    """The modules of ``packages`` (or below them) in ``sys.modules`` of a fresh interpreter after ``imports``."""
    probe = (
        f"import sys; {imports}; packages = {packages!r}; "
        "print(sorted(m for m in sys.modules if any(m == p or m.startswith(p + '.') for p in packages)))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    return list(ast.literal_eval(out.strip()))


def test_the_api_never_imports_the_stage_code() -> None:
    probe = (
        "import sys; from api.main import create_app; from api.cli import build_parser; "
        "heavy = ['cv2', 'cupy', 'scipy', 'workers.stages', 'workers.algorithms', 'gpu_kernels.sift']; "
        f"allowed = {NUMPY_ONLY!r}; "
        "print([m for m in sys.modules if m not in allowed and any(m == h or m.startswith(h + '.') "
        "for h in heavy)])"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_the_api_loads_exactly_the_numpy_only_algorithms() -> None:
    """The list above is what the API loads, so it cannot go stale and let a module through unnoticed."""
    loaded = loaded_after("from api.main import create_app; from api.cli import build_parser", ["workers.algorithms"])
    assert loaded == sorted(NUMPY_ONLY)


def test_core_imports_neither_api_nor_workers() -> None:
    imports = "import core, core.db, core.kinds, core.settings"
    assert loaded_after(imports, ["api", "workers"]) == []
    assert loaded_after(imports, ["core"]) == ["core", "core.db", "core.kinds", "core.settings"]


def test_the_workers_never_import_the_api() -> None:
    imports = "import workers.tasks, workers.celery_app, workers.pipeline, workers.config"
    assert loaded_after(imports, ["api"]) == []
    assert "core.db" in loaded_after(imports, ["core"])  # the job records come from core
