"""Faults that a test-only worker injects into real stage runs; loaded with
``celery -A workers.celery_app worker --include tests.fault.worker_faults``, never by the service.

Files in ``$FOTOSKHEMA_FAULT_DIR`` switch them on, by stage name, for whatever job runs that stage:

- ``hold-<stage>``: the stage, once started (claimed, its heartbeat beating), waits while the file exists;
  it writes ``held-<job>-<stage>`` when it begins to wait, so a test knows the stage is mid-run.
- ``crash-<stage>``: the process running the stage ends at once (``os._exit``), every time, as an
  out-of-memory kill would.

Each start of a stage appends a line to ``started-<job>-<stage>``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from workers import pipeline

_stage_function = pipeline.stage_function


def _with_faults(stage: str) -> Callable[..., dict[str, Any]]:
    run = _stage_function(stage)

    def run_with_faults(ws: Any, cfg: Any, **kwargs: Any) -> dict[str, Any]:
        folder, job = Path(os.environ["FOTOSKHEMA_FAULT_DIR"]), ws.root.name
        with (folder / f"started-{job}-{stage}").open("a") as log:
            log.write(f"{os.getpid()}\n")
        if (folder / f"crash-{stage}").exists():
            os._exit(70)
        hold = folder / f"hold-{stage}"
        if hold.exists():
            (folder / f"held-{job}-{stage}").write_text(str(os.getpid()))
            while hold.exists():
                time.sleep(0.05)
        return run(ws, cfg, **kwargs)

    return run_with_faults


# run_stage looks stage_function up in workers.pipeline at each call, so this wraps every stage it runs.
pipeline.stage_function = _with_faults
