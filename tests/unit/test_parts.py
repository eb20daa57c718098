"""Stages in parts: declared the same way everywhere, and a part is done once whoever does it."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import rasterio

from tests.scenes import make_flight
from workers.pipeline import PARTED_STAGES, PIPELINES, process_directory, run_stage, stage_module, stage_names
from workers.workspace import JobWorkspace


def test_every_stage_in_parts_has_plan_part_and_finish_and_is_parted_in_every_pipeline() -> None:
    for pipeline, specs in PIPELINES.items():
        for spec in specs:
            module = stage_module(spec.name)
            assert (spec.name in PARTED_STAGES) == spec.parted, f"{spec.name} is parted in some pipelines only"
            has_parts = all(hasattr(module, f) for f in ("plan", "run_part", "finish"))
            assert has_parts == spec.parted, f"{pipeline}: {spec.name} parted={spec.parted}, module parts={has_parts}"
            assert spec.parted or hasattr(module, "run")


def test_a_part_key_must_be_a_plain_name(tmp_path: Path) -> None:
    ws = JobWorkspace(tmp_path)
    ws.save_part("load_images", "00001", {"frame": 1})
    assert ws.parts_done("load_images") == {"00001"}
    for bad in ("../x", "a/b", "", "x" * 65, "a.b"):
        with pytest.raises(ValueError):
            ws.save_part("load_images", bad, {})


def test_parts_done_are_not_redone_and_the_outputs_are_the_same(tmp_path: Path) -> None:
    """The job done whole; then two parts of detect_features and two bands of compose_mosaic forgotten, as a
    worker that died with them: running the stages again redoes those parts only, and the mosaic is the same."""
    make_flight(tmp_path / "frames", n_frames=4, frame_size=(320, 240), seed=2)
    process_directory(tmp_path / "frames", tmp_path / "job", {"working_max_px": 320, "block_px": 256})
    ws = JobWorkspace(tmp_path / "job")
    with rasterio.open(ws.mosaic_path()) as src:
        before = src.read()
    features = sorted((ws.root / "features").glob("frame_*.npz"))
    stamps = {p: p.stat().st_mtime_ns for p in features}
    records = sorted((ws.root / "parts" / "detect_features").glob("part_*.json"))
    assert len(records) == 4 and json.loads(records[0].read_text())["_done_by"]
    for record in records[:2]:  # the dead worker's parts: no record, so not done (files may be half there)
        record.unlink()
    for stage in ("detect_features", "compose_mosaic"):
        ws.forget_stage_report(stage)  # the stage never finished
    bands = sorted((ws.root / "parts" / "compose_mosaic").glob("part_*.json"))
    bands[-1].unlink()
    ws.mosaic_path().unlink()
    for name in stage_names("mosaic"):
        run_stage(ws, "mosaic", name)
    redone = [p for p in features if p.stat().st_mtime_ns != stamps[p]]
    assert [p.name for p in redone] == [p.name for p in features[:2]]  # exactly the two forgotten parts
    with rasterio.open(ws.mosaic_path()) as src:
        np.testing.assert_array_equal(src.read(), before)
    report = ws.load_stage_report("detect_features")
    assert report is not None
    summary = report["parts"]
    assert summary["count"] == 4 and sum(v["parts"] for v in summary["by"].values()) == 4
    phases = report["phase_seconds"]  # the serial plan and finish against the parts, timed
    assert set(phases) == {"plan", "parts", "finish"} and all(v >= 0 for v in phases.values())
    # each phase and the wall time are rounded to the millisecond: three roundings' worth over it (0.005 x 3 summed
    # to 0.015000000000000001 against a wall time of 0.015 once)
    assert 0 < sum(phases.values()) <= report["wall_seconds"] + 0.002


def test_parts_on_worker_processes_report_what_went_wrong(tmp_path: Path) -> None:
    """A part's error in a worker process is the stage's; a worker process that dies fails the stage with a
    message, keeping the parts done; a part done is not done again. The workers are gone once the parts are done
    (what they held is returned before the stage's finish)."""
    import multiprocessing

    from tests.unit import part_probe
    from workers.config import MosaicConfig
    from workers.pipeline import PipelineError, parts_in_processes, run_parts
    from workers.tiff_jpeg import BLOCK_CACHE
    from workers.workspace import noop_progress

    ws, cfg = JobWorkspace(tmp_path), MosaicConfig(threads=4)
    BLOCK_CACHE.get("a decoded block", lambda: np.zeros(1000))
    with parts_in_processes(2):
        run_parts(part_probe, "probe", ws, cfg, ["a", "b", "c"], noop_progress)
        assert [ws.load_part("probe", k)["threads"] for k in "abc"] == [1, 1, 1]  # a part a core
        assert all(str(os.getpid()) not in ws.load_part("probe", k)["_done_by"] for k in "abc")
        assert multiprocessing.active_children() == []
        assert BLOCK_CACHE.bytes == 0  # this process's decoded blocks returned while the workers ran
        with pytest.raises(ValueError, match="a bad part"):
            run_parts(part_probe, "probe", ws, cfg, ["a", "bad"], noop_progress)
    with parts_in_processes(2), pytest.raises(PipelineError, match="worker process died during probe"):
        run_parts(part_probe, "probe", ws, cfg, ["d", "die", "e"], noop_progress)
    assert ws.parts_done("probe") >= {"a", "b", "c"} and "die" not in ws.parts_done("probe")
