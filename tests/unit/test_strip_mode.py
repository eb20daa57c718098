"""Mode "strip" end to end on a small synthetic strip (JPEG-in-TIFF, noisy GPS in gps.csv)."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio

from bench.strips import truth_errors
from tests.strip_scenes import make_strip
from workers.pipeline import PipelineError, process_directory, run_stage
from workers.stages.write_report import _warnings
from workers.workspace import JobWorkspace


def test_a_strip_is_registered_at_native_precision(tmp_path: Path) -> None:
    strip = make_strip(tmp_path / "frames", 6, (8000, 400), overlap=0.65, gps_noise_m=1.0, seed=3)
    report = process_directory(tmp_path / "frames", tmp_path / "job", {"mode": "strip", "ccd_segments": 32})
    assert len(report["frames_used"]) == 6 and report["mosaic"]["resolution"] == "native"
    # at the frames' own resolution (their scales jitter 0.5 %), however the adjustment scaled the plane
    assert report["gsd_m"] == pytest.approx(strip.gsd_m, rel=0.015), report["gsd_m"]
    assert report["mosaic"]["photo_px_per_px"] == pytest.approx(1.0, rel=1e-6)
    assert report["triple_overlap_share"] == 1.0  # 65 % forward overlap: scale carried, no warning of it
    assert not any("forward overlap" in warning for warning in report["warnings"])
    assert report["tie_point_rms_px_original"] < 0.5
    errors = truth_errors(strip, tmp_path / "job")
    # the goal: 1 px after one similarity (7 px before the plane was levelled, 0.14 px now)
    assert errors["corner_max_px"] < 1.0, errors
    # absolute: a similarity fitted to 6 fixes of 1 m puts centres within 0.82 m RMS (sigma sqrt(4 / 6))
    assert errors["centre_abs_rms_m"] < 2 * 0.82, errors
    # the corners' precision: six fixes 330 m apart give the strip's heading and scale to 1 m / sqrt(sum d^2) each,
    # which at a corner 9.4 km out is 9.7 m in all; the adjustment's own account is that, and the truth agrees
    precision = report["corner_precision"]
    centres = np.array([strip.frame_center_utm(k) for k in range(6)])
    spread = np.sum((centres - centres.mean(axis=0)) ** 2)
    lever = np.hypot(8000, 400) / 2 * strip.gsd_m
    assert precision["max_m"] == pytest.approx(lever * np.sqrt(2 / spread), rel=0.25), precision
    assert precision["worst_frame"] in {path.name for path in strip.paths}
    assert errors["corner_abs_rms_m"] < 3 * precision["max_m"], (errors, precision)
    # brightness: each frame's gain undoes part of its exposure (Brown & Lowe's prior holds gains near 1: the
    # spread of the two together 0.56x the exposures' own here; gains of 1, as before the plan saw the strip's
    # overlaps, give 1x), and the CCD sub-images' steps are found with a mean error of 0.38 of their 3 % size:
    # their joins every 250 px mostly fall inside JPEG blocks, measured across the block, which takes the rows of
    # many frames to average (these are 6 of 400 rows; 10 % on block edges, tests/unit/test_ccd.py)
    ws = JobWorkspace(tmp_path / "job")
    composed = ws.load_stage_report("compose_mosaic")
    assert composed is not None
    gains = np.array([composed["gains"][path.name][1] for path in strip.paths])
    assert np.std(gains * strip.frame_gains) < 0.7 * np.std(strip.frame_gains), (gains, strip.frame_gains)
    error = np.log(composed["ccd_gains"]) - (np.log(strip.ccd_gains) - np.log(strip.ccd_gains).mean())
    assert np.abs(np.diff(error)).mean() < 0.5 * np.abs(np.diff(np.log(strip.ccd_gains))).mean(), error
    # tie points are measured a pair per part, so a route's pairs spread over workers: a worker that died
    # with two of them leaves only those to redo, and the tie points come out the same
    pairs = ws.load_stage_report("match_strips")
    assert pairs is not None and pairs["parts"]["count"] == pairs["pairs_tried"] >= 5
    # candidates GPS put too far apart on the strip were left out (gap 4 and 5 at 65 %: 1.4 and 1.75 frames apart),
    # and only pairs whose ground does not meet
    index = {path.name: k for k, path in enumerate(strip.paths)}
    assert sorted(pairs["pairs_distant"]) == [
        [strip.paths[a].name, strip.paths[b].name] for a, b in ((0, 4), (0, 5), (1, 5))
    ]
    for a, b in pairs["pairs_distant"]:
        outlines = (strip.corners_ground(index[name]).astype(np.float32) for name in (a, b))
        assert cv2.intersectConvexConvex(*outlines)[0] == 0
    # the others' overlaps as GPS predicts them (400 px frames 35 % apart: 260 px for neighbours, 120 two apart,
    # -20 three apart), from which their coarse registration starts
    predicted = ws.load_part_inputs("match_strips")["overlap_px"]
    assert sorted(predicted) == sorted(ws.load_plan("match_strips"))
    for key, thin in predicted.items():
        gap = int(key.split("_")[1]) - int(key.split("_")[0])
        assert thin == pytest.approx(400 * (1 - 0.35 * gap), abs=20), (key, thin)
    before = {p.name: dict(np.load(p)) for p in sorted((ws.root / "matches").glob("pair_*.npz"))}
    records = sorted((ws.root / "parts" / "match_strips").glob("part_*.json"))
    kept = {p: p.stat().st_mtime_ns for p in records[:1] + records[3:]}
    for record in records[1:3]:
        record.unlink()
    ws.forget_stage_report("match_strips")
    assert run_stage(ws, "mosaic.strip", "match_strips")["pairs"] == pairs["pairs"]
    assert all(p.stat().st_mtime_ns == stamp for p, stamp in kept.items())  # only the lost parts were redone
    assert all(p.exists() for p in records)
    for name, arrays in before.items():
        again = np.load(ws.root / "matches" / name)
        for key, values in arrays.items():
            np.testing.assert_array_equal(again[key], values)


def test_a_strip_whose_frames_share_no_ground_with_both_neighbours_is_warned_of() -> None:
    base = {"frames_rejected": [], "frames_used": []}
    assert not _warnings(base) and not _warnings({**base, "triple_overlap_share": 0.5})
    (warning,) = _warnings({**base, "triple_overlap_share": 0.01})
    assert "1% of the frames" in warning and "55-60 % forward overlap" in warning
    # with the adjustment's account of the corners, the warning says how far out they may be
    precision = {"median_m": 0.35, "max_m": 0.72, "max_photo_px": 2.88, "worst_frame": "strip_000.tif"}
    (warning,) = _warnings({**base, "triple_overlap_share": 0.01, "corner_precision": precision})
    assert "corners known to 0.72 m, 2.9 photo px, 1 sigma, at strip_000.tif" in warning


def test_strip_tie_points_take_one_pair_at_a_time_on_a_gpu_unless_told(monkeypatch: pytest.MonkeyPatch) -> None:
    from workers.config import MosaicConfig
    from workers.parallel import usable_cores
    from workers.stages import match_strips

    assert match_strips.part_threads(MosaicConfig(mode="strip", device="cpu")) == usable_cores()
    assert match_strips.part_threads(MosaicConfig(mode="strip", device="cpu", threads=3)) == 3
    monkeypatch.setattr(match_strips, "resolve_device", lambda requested: "cuda")
    assert match_strips.part_threads(MosaicConfig(mode="strip")) == 1
    assert match_strips.part_threads(MosaicConfig(mode="strip", threads=4)) == 4


def test_parts_on_worker_processes_give_what_threads_give(tmp_path: Path) -> None:
    """``process_directory(processes=2)``: every parted stage's parts done by spawned worker processes, none by this
    one, and the same tie points and mosaic (its pixels and frame index) as this process's threads give."""
    make_strip(tmp_path / "frames", 4, (4000, 400), overlap=0.65, gps_noise_m=1.0, seed=5)
    options = {"mode": "strip", "ccd_segments": 32}
    process_directory(tmp_path / "frames", tmp_path / "threads", options)
    process_directory(tmp_path / "frames", tmp_path / "processes", options, processes=2)
    here = f"{socket.gethostname()}:{os.getpid()}"
    for stage in ("load_images", "match_strips", "compose_mosaic"):
        report = JobWorkspace(tmp_path / "processes").load_stage_report(stage)
        assert report is not None and here not in report["parts"]["by"] and len(report["parts"]["by"]) <= 2
    for name in ("mosaic.tif", "frame_index.tif"):
        with rasterio.open(tmp_path / "threads" / name) as a, rasterio.open(tmp_path / "processes" / name) as b:
            assert np.array_equal(a.read(), b.read()) and np.array_equal(a.read_masks(1), b.read_masks(1))
    matches = sorted((tmp_path / "threads" / "matches").glob("pair_*.npz"))
    assert matches and [p.name for p in matches] == sorted(
        p.name for p in (tmp_path / "processes" / "matches").glob("*.npz")
    )
    for path in matches:
        theirs = np.load(tmp_path / "processes" / "matches" / path.name)
        for key, values in np.load(path).items():
            np.testing.assert_array_equal(theirs[key], values)
    # the photos are checked on the worker processes too: the same entries, and a bad one named
    assert JobWorkspace(tmp_path / "processes").load_inputs() == JobWorkspace(tmp_path / "threads").load_inputs()
    (tmp_path / "frames" / "strip_009.tif").write_bytes(b"not a TIFF")
    with pytest.raises(PipelineError, match="strip_009.tif: "):
        process_directory(tmp_path / "frames", tmp_path / "bad", options, processes=2)
