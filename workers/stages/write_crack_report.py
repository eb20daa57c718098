"""Stage ``write_crack_report``: the crack survey's outputs.

Per load stage a rectified COG (a local engineering CRS in mm on the rectification plane, pixel (col, row)
centred on the plane point (col, row) * mm_per_px, so y runs down the specimen as in a plate's model frame)
and an overlay PNG; for all stages ``cracks.geojson`` (3D polylines in the specimen model's mm),
``cracks.csv`` and ``report.json``.
"""

from __future__ import annotations

import csv
import io
from typing import Any

import cv2
import numpy as np
from rasterio.windows import Window

from workers.algorithms.cracks import Crack
from workers.algorithms.specimen import Surface
from workers.config import CrackSurveyConfig
from workers.raster_io import open_block_writer, translate_to_cog
from workers.workspace import JobWorkspace, ProgressFn, atomic_path, noop_progress

# A local engineering frame in mm (no datum on Earth): GeoTIFF keeps it as a user-defined projected CS in
# millimetres; raster Y grows down the specimen with the rows (a positive pixel height in the transform).
SPECIMEN_CRS = (
    'LOCAL_CS["specimen rectification plane (mm)",LOCAL_DATUM["specimen",32767],'
    'UNIT["millimetre",0.001],AXIS["x",EAST],AXIS["y",SOUTH]]'
)
OVERSAMPLING_WARNING = 2.0  # warn when the raster is this many times finer than the photos' own sampling
STATUS_BGR = {"first": (0, 200, 255), "new": (0, 0, 255), "grown": (255, 0, 255), "unchanged": (0, 200, 0)}
CSV_FIELDS = (
    "stage",
    "stage_label",
    "load",
    "id",
    "length_mm",
    "mean_width_mm",
    "max_width_mm",
    "orientation_deg",
    "status",
    "growth_mm",
    "x_min_mm",
    "y_min_mm",
    "x_max_mm",
    "y_max_mm",
)


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write the rectified COGs and overlays, ``cracks.geojson``, ``cracks.csv`` and ``report.json``."""
    pairs = ws.load_comparison()
    native = (ws.load_stage_report("rectify_specimen") or {}).get("photo_mm_per_px") or [None] * len(cfg.stages)
    stages, rows, warnings = [], [], []
    for s, stage in enumerate(cfg.stages):
        progress(s / len(cfg.stages), f"load step {s + 1}/{len(cfg.stages)}")
        measured, summary = ws.load_measured_cracks(s)
        cracks = crack_rows(cfg, s, measured, pairs[s - 1]["cracks"] if s > 0 else None)
        image, mask = ws.load_rectified(s)
        _write_cog(ws, s, image, mask, cfg)
        _write_overlay(ws, s, image, cracks, cfg.mm_per_px)
        if native[s] is not None and cfg.mm_per_px < native[s] / OVERSAMPLING_WARNING:
            warnings.append(
                f"load step {stage.label!r}: the photos resolve {native[s]:.3g} mm per pixel on the "
                f"specimen, the raster {cfg.mm_per_px:.3g}: resampled coating grain may be taken "
                "for short cracks; a mm_per_px near the photos' is safer"
            )
        stages.append(
            {
                "index": s,
                "label": stage.label,
                "load": stage.load,
                "coverage": float(mask.mean()),
                "photo_mm_per_px": native[s],
                **summary,
                "rectified": ws.load_step_cog_path(s).name,
                "overlay": ws.load_step_overlay_path(s).name,
                "cracks": cracks,
            }
        )
        rows += cracks
    surface = ws.load_surface()
    ws.save_cracks_geojson(_geojson(rows, surface))
    _write_csv(ws, rows)
    report = {
        "kind": "crack_survey",
        "mm_per_px": cfg.mm_per_px,
        "specimen": cfg.specimen.model_dump(),
        "frame": (
            "paths_mm and bbox_mm: (x, y) mm on the rectification plane, x right, y down, raster pixel "
            "(col, row) centred on (x, y) / mm_per_px; cracks.geojson: specimen model (X, Y, Z) mm"
        ),
        "plane": surface.frame.to_json(),
        "photos": ws.load_orientation(),
        "stages": stages,
        "comparisons": [{k: v for k, v in p.items() if k != "cracks"} for p in pairs],
        "warnings": warnings,
    }
    ws.save_report(report)
    progress(1.0, "report written")
    return {"stages": len(stages), "cracks": len(rows)}


def crack_rows(
    cfg: CrackSurveyConfig, s: int, cracks: list[Crack], matches: list[dict[str, Any]] | None
) -> list[dict[str, Any]]:
    """Every crack of stage ``s`` with its status against the stage before ("first" for the first stage)."""
    stage = cfg.stages[s]
    rows = []
    for k, crack in enumerate(cracks):
        match = matches[k] if matches is not None else {"status": "first", "growth_mm": None, "previous": []}
        rows.append(
            {
                "stage": s,
                "stage_label": stage.label,
                "load": stage.load,
                "id": k,
                "length_mm": crack.length_mm,
                "mean_width_mm": crack.mean_width_mm,
                "max_width_mm": crack.max_width_mm,
                "orientation_deg": crack.orientation_deg,
                "status": match["status"],
                "growth_mm": match["growth_mm"],
                "previous": match["previous"],
                "bbox_mm": list(crack.bbox_mm),
                "paths_mm": [p.tolist() for p in crack.paths_mm],
            }
        )
    return rows


def _write_cog(ws: JobWorkspace, s: int, image: np.ndarray, mask: np.ndarray, cfg: CrackSurveyConfig) -> None:
    step = cfg.mm_per_px
    tmp = ws.load_step_scratch_path(s)
    height, width = mask.shape
    with open_block_writer(tmp, width, height, SPECIMEN_CRS, [step, 0.0, -step / 2, 0.0, step, -step / 2]) as write:
        write(Window(0, 0, width, height), cv2.cvtColor(image, cv2.COLOR_BGR2RGB), mask)
    translate_to_cog(tmp, ws.load_step_cog_path(s), cfg.cog_compression)
    tmp.unlink(missing_ok=True)


def _write_overlay(ws: JobWorkspace, s: int, image: np.ndarray, cracks: list[dict[str, Any]], mm_per_px: float) -> None:
    """The rectified image with every crack drawn in its status colour."""
    overlay = image.copy()
    for crack in cracks:
        for path in crack["paths_mm"]:
            points = np.rint(np.array(path) / mm_per_px * 4).astype(np.int32).reshape(-1, 1, 2)  # 2 bits subpixel
            cv2.polylines(overlay, [points], False, STATUS_BGR[crack["status"]], 1, cv2.LINE_AA, shift=2)
    ok, png = cv2.imencode(".png", overlay)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    with atomic_path(ws.load_step_overlay_path(s)) as tmp:
        tmp.write_bytes(png.tobytes())


def _geojson(rows: list[dict[str, Any]], surface: Surface) -> dict[str, Any]:
    """The cracks as 3D lines in the specimen model's own coordinates (X, Y, Z mm; Z = 0 on a plate)."""

    def lines(paths: list[list[list[float]]]) -> list[list[list[float]]]:
        return [np.round(surface.lift(np.array(p)), 4).tolist() for p in paths]

    features = [
        {
            "type": "Feature",
            "geometry": {"type": "MultiLineString", "coordinates": lines(row["paths_mm"])},
            "properties": {k: v for k, v in row.items() if k != "paths_mm"},
        }
        for row in rows
    ]
    # not geographic, so RFC 7946 has no CRS member for it: "frame" names the model's frame instead
    return {"type": "FeatureCollection", "units": "mm", "frame": "specimen model", "features": features}


def _write_csv(ws: JobWorkspace, rows: list[dict[str, Any]]) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, CSV_FIELDS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        x0, y0, x1, y1 = row["bbox_mm"]
        writer.writerow({**row, "x_min_mm": x0, "y_min_mm": y0, "x_max_mm": x1, "y_max_mm": y1})
    ws.save_cracks_csv(buffer.getvalue())
