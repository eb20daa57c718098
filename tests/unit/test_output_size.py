"""How large a mosaic may be: no fixed cap, but the disk must hold it and the grid must look like its frames."""

from __future__ import annotations

import numpy as np

from workers.algorithms.mosaic import disk_needed, output_size_problem, polygon_area


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
