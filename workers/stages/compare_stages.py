"""Stage ``compare_stages``: which cracks of each load stage are new, grown or unchanged since the stage before."""

from __future__ import annotations

from typing import Any

from workers.algorithms.crack_geometry import match_cracks
from workers.config import CrackSurveyConfig
from workers.stages.measure_cracks import load_stage_cracks
from workers.workspace import JobWorkspace, ProgressFn, noop_progress, write_json

STATUSES = ("new", "grown", "unchanged")


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``comparison.json``: per consecutive pair of stages, every current crack's status and growth."""
    pairs = []
    previous, _ = load_stage_cracks(ws, 0)
    for s in range(1, len(cfg.stages)):
        progress((s - 1) / max(len(cfg.stages) - 1, 1), f"stage {s + 1}/{len(cfg.stages)}")
        current, _ = load_stage_cracks(ws, s)
        matches = match_cracks(previous, current, cfg.match_tolerance_mm, min_growth_mm=cfg.min_growth_mm)
        entries = [{"id": m.current, "status": m.status, "growth_mm": m.growth_mm, "previous": list(m.previous)}
                   for m in matches]
        counts = {status: sum(m.status == status for m in matches) for status in STATUSES}
        pairs.append({"from": s - 1, "to": s, **counts, "cracks": entries})
        previous = current
    write_json(ws.comparison_file(), {"pairs": pairs})
    progress(1.0, f"{len(pairs)} pair(s)")
    return {"pairs": len(pairs), "new": [p["new"] for p in pairs], "grown": [p["grown"] for p in pairs]}
