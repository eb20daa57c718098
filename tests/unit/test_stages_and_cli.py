"""Stage bookkeeping (idempotency, reports) and the command line."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import rasterio

from api.cli import build_parser, main
from tests.scenes import make_flight
from workers.pipeline import overall_progress, process_directory, run_stage, stage_names
from workers.workspace import JobWorkspace


def test_progress_is_weighted_and_monotonic() -> None:
    values = [overall_progress("mosaic", s, f) for s in stage_names("mosaic") for f in (0.0, 0.5, 1.0)]
    assert values[0] == 0.0 and values[-1] == 100.0 and values == sorted(values)
    with pytest.raises(ValueError):
        overall_progress("mosaic", "no_such_stage", 0.0)


def test_a_finished_stage_is_not_run_again(tmp_path: Path) -> None:
    make_flight(tmp_path / "frames", n_frames=3, frame_size=(320, 240), seed=1)
    process_directory(tmp_path / "frames", tmp_path / "job", {"working_max_px": 320})
    ws = JobWorkspace(tmp_path / "job")
    mtime = ws.mosaic_path().stat().st_mtime_ns
    report = run_stage(ws, "mosaic", "compose_mosaic")
    assert ws.mosaic_path().stat().st_mtime_ns == mtime and report == ws.load_stage_report("compose_mosaic")
    rerun = run_stage(ws, "mosaic", "compose_mosaic", rerun=True)
    assert ws.mosaic_path().stat().st_mtime_ns != mtime and rerun["width"] == report["width"]
    assert not list(ws.root.rglob(".*.tmp")) and not ws.mosaic_scratch_path().exists()


def test_cli_lists_subcommands_and_processes_a_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    choices = next(a for a in build_parser()._actions if a.dest == "command").choices
    assert {"up", "serve", "worker", "process"} <= set(choices)
    make_flight(tmp_path / "frames", n_frames=3, frame_size=(320, 240), seed=2)
    assert main(["process", str(tmp_path / "frames"), "-o", str(tmp_path / "out"), "--set", "working_max_px=320"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames_used"] == 3 and summary["crs"] == "EPSG:32615"
    assert (tmp_path / "out" / "mosaic.tif").exists() and (tmp_path / "out" / "report.json").exists()
    # its parts on two worker processes: the same mosaic, the frames decoded elsewhere
    args = ["process", str(tmp_path / "frames"), "-o", str(tmp_path / "out2"), "--set", "working_max_px=320"]
    assert main([*args, "--processes", "2"]) == 0
    assert json.loads(capsys.readouterr().out)["frames_used"] == 3
    with rasterio.open(tmp_path / "out" / "mosaic.tif") as a, rasterio.open(tmp_path / "out2" / "mosaic.tif") as b:
        assert np.array_equal(a.read(), b.read())
    parts = json.loads((tmp_path / "out2" / "reports" / "load_images.json").read_text())["parts"]["by"]
    assert parts and str(os.getpid()) not in {who.rsplit(":", 1)[1] for who in parts}


def test_cli_explains_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty").mkdir()
    assert main(["process", str(tmp_path / "empty"), "-o", str(tmp_path / "out")]) == 1
    assert "at least 2" in capsys.readouterr().err
    make_flight(tmp_path / "frames", n_frames=2, frame_size=(320, 240), seed=2)
    assert main(["process", str(tmp_path / "frames"), "-o", str(tmp_path / "o2"), "--set", "ratio_test=2"]) == 1
    assert "ratio_test" in capsys.readouterr().err


def test_the_mosaic_does_not_depend_on_the_window_size(tmp_path: Path) -> None:
    """Composing window by window (bounded memory) leaves no trace at window edges."""
    import numpy as np
    import rasterio

    make_flight(tmp_path / "frames", n_frames=4, frame_size=(400, 300), seed=9)
    process_directory(tmp_path / "frames", tmp_path / "job", {"working_max_px": 400, "block_px": 1024})
    ws = JobWorkspace(tmp_path / "job")
    with rasterio.open(ws.mosaic_path()) as src:
        whole, whole_mask = src.read(), src.dataset_mask()
    config = ws.load_config()
    ws.save_config({**config, "block_px": 256})
    run_stage(ws, "mosaic", "compose_mosaic", rerun=True)
    with rasterio.open(ws.mosaic_path()) as src:
        assert src.width > 256 and src.height > 256  # several windows in each direction
        assert np.array_equal(src.dataset_mask(), whole_mask)
        assert np.abs(src.read().astype(int) - whole).max() <= 1  # float rounding only


def test_a_finished_stage_whose_files_were_lost_runs_again(tmp_path: Path) -> None:
    """A retry after working files were lost: the stages whose files are gone run again (not skipped for
    their report), the others are skipped, and the mosaic comes out the same."""
    make_flight(tmp_path / "frames", n_frames=3, frame_size=(320, 240), seed=1)
    process_directory(tmp_path / "frames", tmp_path / "job", {"working_max_px": 320})
    ws = JobWorkspace(tmp_path / "job")
    with rasterio.open(ws.mosaic_path()) as src:
        before = src.read()
    features = sorted((ws.root / "features").iterdir())
    mtimes = {p: p.stat().st_mtime_ns for p in features}
    (ws.root / "work" / "frame_0001.npy").unlink()  # a lost working copy
    ws.mosaic_path().unlink()
    assert not ws.stage_outputs_present("load_images") and ws.stage_outputs_present("detect_features")
    for name in stage_names("mosaic"):
        run_stage(ws, "mosaic", name)
    assert (ws.root / "work" / "frame_0001.npy").exists()
    assert {p: p.stat().st_mtime_ns for p in features} == mtimes  # detect_features was skipped
    with rasterio.open(ws.mosaic_path()) as src:
        np.testing.assert_array_equal(src.read(), before)


def test_every_stage_names_the_files_it_writes(tmp_path: Path) -> None:
    from workers.pipeline import PIPELINES

    ws = JobWorkspace(tmp_path)
    ws.save_config({"stages": [{"label": "0 kN"}, {"label": "5 kN"}]})
    for pipeline in PIPELINES:
        for name in stage_names(pipeline):
            assert not ws.stage_outputs_present(name), f"{name} names no file it writes"
