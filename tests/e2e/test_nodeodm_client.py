"""End to end with WebODM's own NodeODM client (PyODM): a real Redis, Celery worker and uvicorn; the photos go
up in parallel as PyODM sends them, the task runs, and its all.zip comes back in ODM's layout."""

from __future__ import annotations

from pathlib import Path

import pytest
import rasterio

from tests.conftest import LiveService
from tests.scenes import make_flight

pytestmark = pytest.mark.e2e


def test_pyodm_runs_a_task_and_downloads_its_assets(live_service: LiveService, tmp_path: Path) -> None:
    from pyodm import Node
    from pyodm.types import TaskStatus

    flight = make_flight(tmp_path / "flight", n_frames=4, frame_size=(480, 360), seed=5)
    node = Node.from_url(f"{live_service.url}?token={live_service.token}", timeout=60)
    assert node.info().engine == "fotoskhema" and node.version_greater_or_equal_than("1.4.0")
    assert "working-max-px" in {o.name for o in node.options()}
    task = node.create_task([str(p) for p in flight.paths], {"working-max-px": 480, "dsm": True}, name="pyodm")
    task.wait_for_completion(interval=1)
    info = task.info(with_output=0)
    assert info.status == TaskStatus.COMPLETED and info.images_count == 4 and info.progress == 100
    assert info.processing_time > 0 and info.output[-1] == "Done" and any("dsm" in line for line in info.output)
    assets = Path(task.download_assets(str(tmp_path / "assets")))
    with rasterio.open(assets / "odm_orthophoto" / "odm_orthophoto.tif") as src:
        assert src.crs.to_epsg() == flight.epsg and src.overviews(1)
    assert (assets / "odm_report" / "report.json").exists() and (assets / "task_output.txt").exists()
    assert task.remove()
