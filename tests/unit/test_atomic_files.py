"""The workspace's atomic writes: a file appears whole or not at all, the folder is made when missing, and nothing
of a failed write is left beside it."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from workers.workspace import JobWorkspace, atomic_file, atomic_path


class Interrupted(Exception):
    pass


def _half_write_path(target: Path) -> None:
    with atomic_path(target) as tmp:
        tmp.write_text('{"new": ')
        raise Interrupted


def _half_write_file(target: Path) -> None:
    with atomic_file(target) as file:
        file.write(b'{"new": ')
        raise Interrupted


@pytest.mark.parametrize("half_write", [_half_write_path, _half_write_file])
def test_a_failed_write_leaves_the_old_file_and_no_temporary(
    tmp_path: Path, half_write: Callable[[Path], None]
) -> None:
    target = tmp_path / "part_00001.json"
    target.write_text('{"old": true}')
    with pytest.raises(Interrupted):
        half_write(target)
    assert target.read_text() == '{"old": true}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["part_00001.json"]


def test_writes_make_their_folder_and_leave_only_the_file(tmp_path: Path) -> None:
    ws = JobWorkspace(tmp_path / "job")
    ws.save_part("match_features", "00000_00001", {"pair": [0, 1], "h": np.eye(3)})
    ws.save_part("match_features", "00000_00001", {"pair": [0, 1], "again": True})  # replaced whole
    assert ws.load_part("match_features", "00000_00001") == {"pair": [0, 1], "again": True}
    image = np.arange(24, dtype=np.uint8).reshape(2, 4, 3)
    ws.save_working_image(0, image)
    assert np.array_equal(ws.load_working_image(0), image)
    points = np.array([[1.5, 2.5], [3.0, 4.0]])
    ws.save_matches((0, 1), points, points + 1.0, np.array([7, 9]), np.array([2, 3]))
    found_i, found_j = ws.load_matches((0, 1))
    assert np.array_equal(found_i, points) and np.array_equal(found_j, points + 1.0)
    left = sorted(str(p.relative_to(ws.root)) for p in ws.root.rglob("*") if p.is_file())
    assert not [name for name in left if Path(name).name.startswith(".")], left  # no temporary beside them
