"""What a worker that composes drone mosaics loads: not SciPy nor pyproj (about 50 and 20 MiB of its memory,
more than a 6-frame flight's data), which only jobs that need them import."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_mosaic_stages_load_neither_scipy_nor_pyproj() -> None:
    code = (
        "import sys\n"
        "from workers.pipeline import pipeline_key, stage_function, stage_names\n"
        "for stage in stage_names(pipeline_key('mosaic', {})):\n"
        "    stage_function(stage)\n"
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'scipy', 'pyproj'}))\n"
    )
    found = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert found.stdout.strip() == "[]", found.stdout + found.stderr
