"""Working copies read by window (``workspace.NpyWindows``): the array's own pixels, from any thread, and none of
the file left in the process's resident set, where a memory map keeps every page it touched."""

from __future__ import annotations

import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from workers.workspace import JobWorkspace, NpyWindows


def test_windows_are_the_arrays_own_slices_from_any_thread(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    image = rng.integers(0, 256, (301, 457, 3), dtype=np.uint8)
    ws = JobWorkspace(tmp_path)
    ws.save_working_image(4, image)
    reader = ws.compose_image_windows(4)
    assert reader.shape == image.shape and reader.dtype == np.uint8
    windows = [(slice(r, r + h), slice(c, c + w)) for r, h, c, w in rng.integers(0, 320, (200, 4))]
    windows += [(slice(0, 301), slice(0, 457)), (slice(-5, None), slice(None, 3)), (slice(10, 10), slice(0, 5))]
    with ThreadPoolExecutor(4) as pool:
        got = list(pool.map(reader.__getitem__, windows))
    for key, window in zip(windows, got, strict=True):
        np.testing.assert_array_equal(window, image[key])
        assert window.flags.c_contiguous


def test_an_ortho_frame_is_read_where_there_is_one(tmp_path: Path) -> None:
    ws = JobWorkspace(tmp_path)
    ws.save_working_image(0, np.zeros((8, 9, 3), np.uint8))
    ws.save_ortho_image(0, np.full((10, 12, 3), 7, np.uint8))
    np.testing.assert_array_equal(ws.compose_image_windows(0)[2:5, 3:11], np.full((3, 8, 3), 7, np.uint8))


def test_a_file_that_is_not_an_image_or_is_cut_short_is_refused(tmp_path: Path) -> None:
    np.save(tmp_path / "flat.npy", np.zeros((4, 5), np.uint8))
    with pytest.raises(ValueError, match="not a C-ordered"):
        NpyWindows(tmp_path / "flat.npy")
    np.save(tmp_path / "cut.npy", np.zeros((40, 50, 3), np.uint8))
    data = (tmp_path / "cut.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(data[: len(data) // 2])
    reader = NpyWindows(tmp_path / "cut.npy")
    np.testing.assert_array_equal(reader[0:5, 0:50], np.zeros((5, 50, 3), np.uint8))
    with pytest.raises(ValueError, match="shorter than its header"):
        reader[30:40, 0:50]


def rss_file_mib() -> float:
    """This process's file-backed resident pages (RssFile), MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("RssFile:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no RssFile")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/status (Linux)")
def test_reading_every_window_leaves_nothing_of_the_file_resident(tmp_path: Path) -> None:
    """The same 48 MiB image read window by window: through a memory map its pages join the resident set (the
    measure works), through NpyWindows they do not."""
    image = np.random.default_rng(0).integers(0, 256, (2048, 8192, 3), dtype=np.uint8)
    np.save(tmp_path / "big.npy", image)
    del image
    reader = NpyWindows(tmp_path / "big.npy")
    before = rss_file_mib()
    total = sum(
        int(reader[r : r + 256, c : c + 512][0, 0, 0]) for r in range(0, 2048, 256) for c in range(0, 8192, 512)
    )
    by_windows = rss_file_mib() - before
    mapped = np.load(tmp_path / "big.npy", mmap_mode="r")
    before = rss_file_mib()
    assert sum(int(np.ascontiguousarray(mapped[r : r + 256, c : c + 512])[0, 0, 0]) for r in range(0, 2048, 256)
               for c in range(0, 8192, 512)) == total  # fmt: skip
    by_map = rss_file_mib() - before
    assert by_map > 40 and by_windows < 4, (by_map, by_windows)
