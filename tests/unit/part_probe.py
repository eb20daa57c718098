"""A stage module for tests of parts on worker processes (``workers.pipeline.parts_in_processes``): its parts, run
in a spawned process, import it by name. ``run_part`` answers its key, fails on "bad" and kills its process on
"die"."""

from __future__ import annotations

import os
from typing import Any


def run_part(ws: Any, cfg: Any, key: str) -> dict[str, Any]:
    if key == "bad":
        raise ValueError("a bad part")
    if key == "die":
        os._exit(9)  # as the kernel's OOM killer would
    return {"key": key, "threads": cfg.threads}
