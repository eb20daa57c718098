"""The workspace's typed records survive the round trip through their JSON files, and a pipeline run's
artifacts read back as those records."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from workers.records import (
    Alignment,
    Coverage,
    DroppedPair,
    Frame,
    Georef,
    PairRecord,
    PairResidual,
    RejectedFrame,
)
from workers.workspace import JobWorkspace


def _frame(index: int, gps: dict[str, float | None] | None = None) -> Frame:
    return Frame(
        index,
        f"IMG_{index}.JPG",
        f"/photos/IMG_{index}.JPG",
        4000,
        3000,
        2048,
        1536,
        0.512,
        gps=gps,
        focal_length_35mm=24.0,
        yaw=-130.5,
        pitch=-89.9,
        roll=0.0,
    )


def _same(a: object, b: object) -> None:
    """Equal field by field, arrays by value (dataclass equality would compare arrays by identity)."""
    assert type(a) is type(b)
    for name in a.__dataclass_fields__:  # type: ignore[attr-defined]
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            np.testing.assert_array_equal(x, y)
        elif isinstance(x, dict) and x and isinstance(next(iter(x.values())), np.ndarray):
            assert x.keys() == y.keys()
            for k in x:
                np.testing.assert_array_equal(x[k], y[k])
        elif isinstance(x, list) and x and isinstance(x[0], np.ndarray):
            assert len(x) == len(y)
            for u, v in zip(x, y, strict=True):
                np.testing.assert_array_equal(u, v)
        else:
            assert x == y, name


def test_frames_and_rejections_round_trip(tmp_path: Path) -> None:
    ws = JobWorkspace(tmp_path)
    frames = [_frame(0, {"lat": 50.8, "lon": -0.13, "alt": 61.2}), _frame(2)]
    ws.save_frames(frames, [RejectedFrame(1, "IMG_1.JPG", "could not be decoded")])
    assert ws.load_frames() == frames
    assert ws.load_rejected_frames() == [RejectedFrame(1, "IMG_1.JPG", "could not be decoded")]


def test_pairs_keep_their_model_and_its_kind(tmp_path: Path) -> None:
    ws = JobWorkspace(tmp_path)
    H = np.array([[1.0, 0.01, 250.5], [-0.01, 1.0, -3.25], [1e-6, 0.0, 1.0]])
    pairs = [
        PairRecord(0, 1, 800, 412, True, "H", H, tie_points=300),
        PairRecord(1, 2, 40, 3, False, "H", None),
        PairRecord(0, 2, 90, 60, True, "F", H.T, tie_points=60),
    ]
    ws.save_pairs(pairs)
    for saved, loaded in zip(pairs, ws.load_pairs(), strict=True):
        _same(saved, loaded)
    on_disk = json.loads((tmp_path / "pairs.json").read_text())["pairs"]
    assert "H" in on_disk[0] and "F" in on_disk[2] and "tie_points" not in on_disk[1]


def test_alignment_georef_and_coverage_round_trip(tmp_path: Path) -> None:
    ws = JobWorkspace(tmp_path)
    rng = np.random.default_rng(3)
    alignment = Alignment(
        reference=1,
        homographies={0: rng.normal(size=(3, 3)), 1: np.eye(3)},
        rejected=[RejectedFrame(2, "c.jpg", "alignment folds or stretches the frame")],
        tie_point_rms_px=0.93,
        tie_points=1800,
        dropped_pairs=[DroppedPair(0, 2, "inconsistent")],
        pair_residuals=[PairResidual(0, 1, 0.9, 3.1)],
        mode="ortho",
        frame_sizes={0: (2048, 900)},
        ground_z=12.5,
    )
    ws.save_alignment(alignment)
    _same(ws.load_alignment(), alignment)
    georef = Georef(
        georeferenced=True,
        reason="",
        epsg=32630,
        plane_to_map=rng.normal(size=(3, 3)),
        gsd_m=0.0169,
        width=3820,
        height=3716,
        transform=[0.0169, 0.0, 699000.0, 0.0, -0.0169, 5630000.0],
        output_to_plane=rng.normal(size=(3, 3)),
        gps_frames=6,
        gps_residual_rms_m=0.85,
        gps_residuals_m={"a.jpg": 0.4},
    )
    ws.save_georef(georef)
    _same(ws.load_georef(), georef)
    coverage = Coverage([rng.normal(size=(5, 2)), rng.normal(size=(3, 2))], 0.71)
    ws.save_coverage(coverage)
    _same(ws.load_coverage(), coverage)


def test_composed_frames_take_the_size_orthorectification_cut_them_to(tmp_path: Path) -> None:
    ws = JobWorkspace(tmp_path)
    ws.save_frames([_frame(0), _frame(1)], [])
    ws.save_alignment(
        Alignment(0, {0: np.eye(3), 1: np.eye(3)}, [], None, 0, mode="ortho", frame_sizes={1: (2048, 700)})
    )
    composed = ws.load_composed_frames()
    assert (composed[0].width, composed[0].height) == (2048, 1536)
    assert (composed[1].width, composed[1].height) == (2048, 700) and composed[1].name == "IMG_1.JPG"


@pytest.mark.parametrize("missing", ["frames.json", "alignment.json"])
def test_a_missing_artifact_is_an_error_not_an_empty_record(tmp_path: Path, missing: str) -> None:
    ws = JobWorkspace(tmp_path)
    with pytest.raises(FileNotFoundError):
        ws.load_frames() if missing == "frames.json" else ws.load_alignment()
