"""Faults that a test-only worker injects into real stage runs; loaded with
``celery -A workers.celery_app worker --include tests.fault.worker_faults``, never by the service.

Files in ``$FOTOSKHEMA_FAULT_DIR`` switch them on, by stage name, for whatever job runs that stage:

- ``hold-<stage>``: the stage, once started (claimed, its heartbeat beating), waits while the file exists;
  it writes ``held-<job>-<stage>`` when it begins to wait, so a test knows the stage is mid-run.
- ``crash-<stage>``: the process running the stage ends at once (``os._exit``), every time, as an
  out-of-memory kill would.
- ``hold-part-<stage>``, ``crash-part-<stage>``: the same in each part of a stage done in parts; a held part
  writes ``held-part-<job>-<stage>-<pid>``.
- ``fail-once-part-<stage>``: the first part of the stage to start raises an error (a crash that is not the
  data's: a worker's disk or network for a moment); the parts after it run as usual.

Each start of a stage (its whole run, or the plan of a stage in parts) appends a line to
``started-<job>-<stage>``; each start of a part, to ``started-part-<job>-<stage>``.
"""

from __future__ import annotations

import contextlib
import os
import time
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

from workers import pipeline
from workers.workspace import atomic_path

_stage_module = pipeline.stage_module


def _fault(kind: str, stage: str, ws: Any) -> None:
    """Log a start of ``kind`` ("" for a stage, "part-" for a part), then crash or hold if switched on."""
    folder, job = Path(os.environ["FOTOSKHEMA_FAULT_DIR"]), ws.root.name
    with (folder / f"started-{kind}{job}-{stage}").open("a") as log:
        log.write(f"{os.getpid()}\n")
    if (folder / f"crash-{kind}{stage}").exists():
        os._exit(70)
    if kind and (folder / f"fail-once-{kind}{stage}").exists():
        with contextlib.suppress(FileExistsError):
            (folder / f"failed-once-{job}-{stage}").open("x").close()  # the first part only
            raise RuntimeError("a part's worker lost its scratch disk for a moment")
    hold = folder / f"hold-{kind}{stage}"
    if hold.exists():
        marker = f"held-{kind}{job}-{stage}" + (f"-{os.getpid()}" if kind else "")
        with atomic_path(folder / marker) as tmp:  # whole when it appears: a test reads the pid once it sees it
            tmp.write_text(str(os.getpid()))
        while hold.exists():
            time.sleep(0.05)


def _wrapped(stage: str, fn: Callable[..., Any], kind: str) -> Callable[..., Any]:
    def with_faults(ws: Any, cfg: Any, *args: Any, **kwargs: Any) -> Any:
        _fault(kind, stage, ws)
        return fn(ws, cfg, *args, **kwargs)

    return with_faults


def _with_faults(stage: str) -> types.ModuleType:
    module = _stage_module(stage)
    faulty = types.ModuleType(module.__name__)
    faulty.__dict__.update(module.__dict__)
    if hasattr(module, "plan"):
        faulty.plan = _wrapped(stage, module.plan, "")
        faulty.run_part = _wrapped(stage, module.run_part, "part-")
    else:
        faulty.run = _wrapped(stage, module.run, "")
    return faulty


# the stage runners look stage_module up in workers.pipeline at each call, so this wraps every stage they run
pipeline.stage_module = _with_faults
