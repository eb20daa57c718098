"""How large a mosaic may be: no fixed cap, but the disk must hold it and the grid must look like its frames."""

from __future__ import annotations

import numpy as np
import pytest

from workers.algorithms.mosaic import disk_needed, output_size_problem, photo_px_per_plane_px, polygon_area


def test_a_gigapixel_strip_is_fine_where_the_disk_holds_it() -> None:
    width, height = 353_000, 47_000  # a real 1600-frame route's mosaic: 16.6 Gpx, far past the old 4 Gpx cap
    frames_px = 1600 * 75_000 * 1_800 * 0.5  # half of each frame is new ground
    need = disk_needed(width, height)
    assert 30e9 < need < 40e9  # the COG and little more: the bands become its tiles (workers/cog_writer.py)
    assert output_size_problem(width, height, frames_px, free_bytes=need + 1) is None
    problem = output_size_problem(width, height, frames_px, free_bytes=need // 2)
    assert problem is not None and "GB of free disk" in problem and f"{need / 1e9:.1f}" in problem
    # lossy JPEG tiles take far less: a disk too small for the deflate COG holds the JPEG one
    assert disk_needed(width, height, "jpeg") < need / 2
    assert output_size_problem(width, height, frames_px, free_bytes=need // 2, compression="jpeg") is None


def test_a_grid_far_larger_than_its_frames_is_a_broken_alignment() -> None:
    problem = output_size_problem(2_000_000, 2_000_000, frames_px=6 * 2048 * 1152, free_bytes=10**18)
    assert problem is not None and "degenerate" in problem
    assert output_size_problem(3819, 3710, frames_px=6 * 2048 * 1152, free_bytes=10**12) is None


def test_polygon_area() -> None:
    square = [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]
    assert polygon_area(np.array(square)) == 100.0
    assert polygon_area(np.array(square[::-1])) == 100.0


def test_photo_px_per_plane_px_is_measured_through_the_homography() -> None:
    """A working copy at 1/8 of a 75000 x 1800 photo, placed on a plane the adjustment shrank to 0.92 and
    turned: one plane px spans 8 / 0.92 photo px, not the 8 the working copy alone says."""
    turn = np.deg2rad(30.0)
    H = np.array([[np.cos(turn), -np.sin(turn), 40.0], [np.sin(turn), np.cos(turn), -7.0], [0.0, 0.0, 1.0]])
    H[:2, :2] *= 0.92
    assert photo_px_per_plane_px(H, 9375, 225, 75_000, 1_800) == pytest.approx(8 / 0.92, rel=1e-9)
    assert photo_px_per_plane_px(np.eye(3), 2000, 1500, 4000, 3000) == pytest.approx(2.0, rel=1e-9)
