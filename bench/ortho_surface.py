"""What each ``ortho_surface`` costs and buys: the plane, the tie points' surface and dense stereo between
neighbouring frames, on the same adjusted job, in the same run.

Run by hand from the repository root::

    .venv/bin/python bench/ortho_surface.py [DIR ...] [--no-terrain]

``DIR``s default to ``../shared/data/drone_brighton_strip1`` where present; the rendered scenes of
``tests/unit/test_ortho_truth.py`` (``tests/terrain_scenes.py``) are added unless ``--no-terrain``: the smooth
terrain (12 frames of 640 x 480 px over 6 m hills) and the buildings (8 frames of 480 x 360 px from 40 m over
2 m hills with four box-shaped buildings whose roofs stand 4-7 m above the datum, ``BUILDINGS``). Each flight
goes through the whole ortho pipeline once (timed); then, for each surface, ``orthorectify_frames`` and
``compose_mosaic`` run again on a copy of the adjusted job. Printed per
surface: the orthorectification stage's seconds and their ratio to the tie points' surface's, the surface's
own seconds (dense: pairs rectified, matched and fused) as a share of the whole pipeline, the pairs, dense
points and coverage the report gives, and on the rendered terrain the surface's height error against the
terrain (RMS over the cameras' span, 10 m beyond) and the mosaic's mean colour error over the relief (more
than 1 m off the ortho plane) and on level ground; on the buildings, how far each roof shows from where it
stands (median and largest, m), the colour error on the buildings and 2 m around them, and the surface's
height error on the roofs (RMS, 0.5 m in from their eaves).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path
from statistics import median

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.terrain_scenes import (  # noqa: E402
    TerrainFlight,
    block_colour_error,
    level_ground_colour_error,
    make_buildings_flight,
    make_terrain_flight,
    relief_colour_error,
    roof_height_rms,
    roof_shifts_m,
    surface_height_rms,
)
from workers.pipeline import process_directory, run_stage  # noqa: E402
from workers.workspace import JobWorkspace  # noqa: E402

SURFACES = ("plane", "tie_points", "dense")


def measure(name: str, frames: Path, work: Path, options: dict, flight: TerrainFlight | None) -> None:
    started = time.perf_counter()
    process_directory(frames, work / "job", {"mode": "ortho", "ortho_surface": "plane", **options})
    pipeline_s = time.perf_counter() - started
    print(f"\n{name}: whole ortho pipeline {pipeline_s:.1f} s (plane)")
    base = JobWorkspace(work / "job")
    rows = {}
    for kind in SURFACES:
        ws = JobWorkspace(work / kind)
        shutil.copytree(base.root, ws.root)
        ws.save_config({**ws.load_config(), "ortho_surface": kind})
        t0 = time.perf_counter()
        run_stage(ws, "mosaic.ortho", "orthorectify_frames", rerun=True)
        stage_s = time.perf_counter() - t0
        for stage in ("compose_mosaic", "write_report"):
            run_stage(ws, "mosaic.ortho", stage, rerun=True)
        rows[kind] = (ws, stage_s, ws.load_report()["ortho_surface"])
    reference = rows["tie_points"][1]
    print(
        f"{'surface':<11} {'stage s':>8} {'x tie':>6} {'surface s':>10} {'% pipe':>7} {'pairs':>6} {'points':>8} "
        f"{'cover':>6} {'cell m':>7} {'height RMS m':>13} {'relief err':>11} {'level err':>10}"
    )
    for ws, stage_s, note in rows.values():
        own = note.get("seconds")
        z0 = ws.load_alignment().ground_z
        truth = ["–", "–", "–"]
        if flight is not None:
            rms = surface_height_rms(flight, ws)
            truth = [
                "–" if rms is None else f"{rms:.3f}",
                f"{relief_colour_error(flight, ws.mosaic_path(), z0)[0]:.2f}",
                f"{level_ground_colour_error(flight, ws.mosaic_path(), z0)[0]:.2f}",
            ]
        print(
            f"{note['kind']:<11} {stage_s:8.2f} {stage_s / reference:6.2f} "
            f"{'–' if own is None else f'{own:.2f}':>10} {'–' if own is None else f'{100 * own / pipeline_s:.1f}':>7} "
            f"{note.get('pairs', '–'):>6} {note.get('dense_points', '–'):>8} {note.get('coverage', '–'):>6} "
            f"{note.get('cell_m', '–'):>7} {truth[0]:>13} {truth[1]:>11} {truth[2]:>10}"
        )
    if flight is not None and flight.blocks:
        print(
            f"{'surface':<11} {'roof shift m (median, max)':>27} {'err near buildings':>19} {'roof height RMS m':>18}"
        )
        for ws, _, note in rows.values():
            shifts = sorted(roof_shifts_m(flight, ws.mosaic_path()))
            roof = roof_height_rms(flight, ws)
            print(
                f"{note['kind']:<11} {f'{median(shifts):.2f}, {shifts[-1]:.2f}':>27} "
                f"{block_colour_error(flight, ws.mosaic_path())[0]:19.2f} {'–' if roof is None else f'{roof:.3f}':>18}"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dirs", nargs="*", type=Path)
    parser.add_argument("--no-terrain", action="store_true", help="leave out the rendered terrain")
    args = parser.parse_args()
    dirs = args.dirs or [d for d in [ROOT.parent / "shared/data/drone_brighton_strip1"] if d.is_dir()]
    with tempfile.TemporaryDirectory() as tmp:
        if not args.no_terrain:
            root = Path(tmp) / "terrain"
            flight = make_terrain_flight(root / "frames", rows=3, per_row=4, frame_size=(640, 480), seed=3)
            measure("rendered terrain (12 x 640 x 480)", root / "frames", root, {"gps_sigma_m": 0.05}, flight)
            root = Path(tmp) / "buildings"
            flight = make_buildings_flight(root / "frames")
            measure("rendered buildings (8 x 480 x 360)", root / "frames", root, {"gps_sigma_m": 0.05}, flight)
        for d in dirs:
            measure(d.name, d, Path(tmp) / d.name, {}, None)


if __name__ == "__main__":
    main()
