"""Stage ``compare_stages``: which cracks of each load stage are new, grown or unchanged since the stage before."""

from __future__ import annotations

from typing import Any

from workers.algorithms.cracks import match_cracks
from workers.config import CrackSurveyConfig
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

STATUSES = ("new", "grown", "unchanged")


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``comparison.json``: per consecutive pair of stages, every current crack's status and growth."""
    pairs = []
    previous, _ = ws.load_measured_cracks(0)
    for s in range(1, len(cfg.stages)):
        progress((s - 1) / max(len(cfg.stages) - 1, 1), f"load step {s + 1}/{len(cfg.stages)}")
        current, _ = ws.load_measured_cracks(s)
        matches = match_cracks(previous, current, cfg.match_tolerance_mm, min_growth_mm=cfg.min_growth_mm)
        entries = [
            {"id": m.current, "status": m.status, "growth_mm": m.growth_mm, "previous": list(m.previous)}
            for m in matches
        ]
        counts = {status: sum(m.status == status for m in matches) for status in STATUSES}
        pairs.append({"from": s - 1, "to": s, **counts, "cracks": entries})
        previous = current
    ws.save_comparison(pairs)
    progress(1.0, f"{len(pairs)} pair(s)")
    return {"pairs": len(pairs), "new": [p["new"] for p in pairs], "grown": [p["grown"] for p in pairs]}
