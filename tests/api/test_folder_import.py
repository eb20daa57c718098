"""Server-side import of a folder (FOTOSKHEMA_IMPORT_DIRS): nothing outside the allowed directories can be named
(``..``, absolute paths, symbolic links out), a folder of JPEG-in-TIFF strip frames with its gps.csv becomes the
flight's photos and GPS side file, each file checked as an upload is; progress, re-import, cancel, refusals."""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
import time
from datetime import timedelta
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update

from api import folder_import
from api.models import ImportCreate
from core.db import Database, FolderImport, utcnow
from tests.conftest import user_headers
from tests.scenes import make_flight, write_bad_files
from tests.strip_scenes import make_strip

FRAME = (512, 256)  # (width, height) of the strip frames: tiled JPEG in TIFF, 2 x 1 tiles


@pytest.fixture(scope="module")
def strip_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three JPEG-in-TIFF strip frames and their gps.csv, rendered once."""
    folder = tmp_path_factory.mktemp("strip")
    make_strip(folder, n_frames=3, frame_size=FRAME, seed=4)
    return folder


@pytest.fixture
def root(tmp_path: Path, api_settings, strip_dir: Path) -> Path:
    """An import directory holding route_17/frames (copies of the strip) and a folder beside it, outside."""
    base = tmp_path / "import"
    shutil.copytree(strip_dir, base / "route_17" / "frames")
    (tmp_path / "outside").mkdir()
    shutil.copy(strip_dir / "strip_000.tif", tmp_path / "outside" / "secret.tif")
    api_settings.import_dirs = [base]
    return base


def new_flight(client: TestClient, headers: dict[str, str] | None = None) -> int:
    return int(client.post("/api/flights", json={"name": "route 17"}, headers=headers).json()["id"])


def start(client: TestClient, flight: int, **body) -> dict:
    response = client.post(f"/api/flights/{flight}/imports", json=body)
    return {**response.json(), "http": response.status_code}


def finished(client: TestClient, flight: int, import_id: int, timeout: float = 60) -> dict:
    deadline = time.monotonic() + timeout
    while (record := client.get(f"/api/flights/{flight}/imports/{import_id}").json())["status"] == "running":
        assert time.monotonic() < deadline, f"import still running: {record}"
        time.sleep(0.1)
    return record


def test_import_is_off_until_ops_name_a_directory(client: TestClient) -> None:
    answer = start(client, new_flight(client), path="route_17/frames")
    assert answer["http"] == 403 and "FOTOSKHEMA_IMPORT_DIRS" in answer["detail"]
    assert client.get("/api/config").json()["import_dirs"] == 0


def test_a_folder_of_strip_frames_with_its_gps_csv_is_imported(
    client: TestClient, api_settings, root: Path, strip_dir: Path
) -> None:
    flight = new_flight(client)
    answer = start(client, flight, root=0, path="route_17/frames")
    assert answer["http"] == 202, answer
    assert answer["total"] == 3 and answer["gps"]["file"] == "gps.csv" and answer["gps"]["fixes"] == 3
    record = finished(client, flight, answer["id"])
    assert record["status"] == "succeeded", record
    assert (record["done"], record["imported"], record["skipped"], record["refused"]) == (3, 3, 0, 0)
    assert record["errors"] == {} and record["bytes_copied"] == 0  # hard links: no disk used
    assert record["gps"]["gps_source"] == {"side_file": 3, "exif": 0, "none": 0}  # summary once the photos are in
    images = client.get(f"/api/flights/{flight}").json()["images"]
    assert [i["filename"] for i in images] == ["strip_000.tif", "strip_001.tif", "strip_002.tif"]
    assert all((i["width"], i["height"]) == FRAME for i in images)
    stored = api_settings.data_dir / "flights" / str(flight)
    for image in images:
        source = root / "route_17" / "frames" / image["filename"]
        kept = stored / "images" / image["stored_name"]
        assert kept.read_bytes() == (strip_dir / image["filename"]).read_bytes()
        assert kept.stat().st_ino == source.stat().st_ino  # a hard link to the source
    assert (stored / "gps.csv").read_text() == (strip_dir / "gps.csv").read_text()  # as PUT /gps stores it
    assert [r["id"] for r in client.get(f"/api/flights/{flight}/imports").json()] == [answer["id"]]
    # importing it again reads nothing it imported before; a new frame is taken
    shutil.copy(write_good_jpeg(root), root / "route_17" / "frames" / "extra.jpg")
    again = finished(client, flight, start(client, flight, path="route_17/frames")["id"])
    assert (again["imported"], again["skipped"], again["status"]) == (1, 3, "succeeded")


def write_good_jpeg(root: Path) -> Path:
    return make_flight(root.parent / "drone", n_frames=1, frame_size=(320, 240), seed=9).paths[0]


@pytest.mark.parametrize(
    ("body", "status", "detail"),
    [
        ({"path": "../outside"}, 422, "path: '../outside' goes up with '..'"),
        ({"path": "route_17/../../outside"}, 422, "goes up with '..'"),
        ({"path": "route_17\\..\\..\\outside"}, 422, "goes up with '..'"),
        ({"path": "/etc"}, 422, "path: '/etc' is absolute"),
        ({"path": "\\\\server\\share"}, 422, "is absolute"),
        ({"path": "C:/frames"}, 422, "is absolute"),
        ({"path": "~/frames"}, 422, "is absolute"),
        ({"path": "escape"}, 422, "path: 'escape' leads outside import directory 0 (a symbolic link)"),
        ({"path": "escape/deeper"}, 422, "path: 'escape/deeper' leads outside import directory 0"),  # even if absent
        ({"path": "route_17/missing"}, 404, "path: no folder 'route_17/missing' in import directory 0"),
        ({"path": "route_17/frames/strip_000.tif"}, 422, "is not a folder"),
        ({"path": "route_17/frames", "root": 1}, 422, "root: this server has 1 import directories"),
        ({"path": "route_17/frames", "root": -1}, 422, "greater than or equal to 0"),
        ({"path": "route_17", "recursive": False}, 422, "no photos"),
        ({"path": "route_17/frames", "extra": 1}, 422, "Extra inputs are not permitted"),
    ],
)
def test_nothing_outside_the_import_directories_can_be_named(
    client: TestClient, api_settings, root: Path, tmp_path: Path, body: dict, status: int, detail: str
) -> None:
    (root / "escape").symlink_to(tmp_path / "outside", target_is_directory=True)
    flight = new_flight(client)
    answer = start(client, flight, **body)
    assert answer["http"] == status, answer
    assert detail in str(answer["detail"])
    assert str(tmp_path) not in str(answer["detail"])  # never a server path
    assert client.get(f"/api/flights/{flight}/imports").json() == []
    assert client.get(f"/api/flights/{flight}").json()["images"] == []


def test_links_and_bad_files_in_the_folder_are_refused_one_by_one(
    client: TestClient, api_settings, root: Path, tmp_path: Path
) -> None:
    frames = root / "route_17" / "frames"
    (frames / "gps.csv").unlink()
    (frames / "leak.tif").symlink_to(tmp_path / "outside" / "secret.tif")  # a link to a file outside
    (frames / "zz_alias.tif").symlink_to(frames / "strip_001.tif")  # a link inside: the same photo twice
    bad = write_bad_files(tmp_path / "bad")
    shutil.copy(bad["not_image"], frames / "notes.jpg")
    shutil.copy(bad["truncated"], frames / "cut.jpg")
    os.mkfifo(frames / "pipe.tif")  # opening it would block for ever
    (frames / "README.txt").write_text("not a photo, not listed")
    sub = frames / "sub"
    sub.mkdir()
    shutil.copy(write_good_jpeg(root), sub / "drone.jpg")
    (sub / "away").symlink_to(tmp_path / "outside", target_is_directory=True)
    flight = new_flight(client)
    answer = start(client, flight, path="route_17/frames", recursive=True)
    assert answer["http"] == 202 and answer["gps"] == {}
    record = finished(client, flight, answer["id"])
    assert record["status"] == "succeeded"
    assert set(record["errors"]) == {"leak.tif", "pipe.tif", "notes.jpg", "cut.jpg", "sub/away/"}
    assert record["errors"]["leak.tif"] == "a symbolic link to a file outside the import directory"
    assert record["errors"]["pipe.tif"] == "not a regular file"
    assert record["errors"]["notes.jpg"].startswith("not a readable image")
    assert record["errors"]["sub/away/"] == "a symbolic link to a folder outside the import directory"
    # strip 0-2, the drone photo in sub/, and zz_alias.tif: the same bytes as strip_001, skipped
    assert (record["imported"], record["skipped"], record["refused"]) == (4, 1, 5)
    names = sorted(i["filename"] for i in client.get(f"/api/flights/{flight}").json()["images"])
    assert names == ["drone.jpg", "strip_000.tif", "strip_001.tif", "strip_002.tif"]
    assert not any(p.name.startswith(".import-") for p in (api_settings.data_dir / "flights").rglob("*"))


def test_a_bad_gps_file_refuses_the_import_before_anything_is_stored(client: TestClient, root: Path) -> None:
    frames = root / "route_17" / "frames"
    text = (frames / "gps.csv").read_text().splitlines()
    text[2] = text[2].replace(text[2].split(",")[1], "95.5")
    (frames / "gps.csv").write_text("\n".join(text) + "\n")
    flight = new_flight(client)
    answer = start(client, flight, path="route_17/frames")
    assert answer["http"] == 422 and answer["detail"].startswith("gps.csv: line 3: latitude")
    assert client.get(f"/api/flights/{flight}/imports").json() == []
    assert client.get(f"/api/flights/{flight}").json()["images"] == []


def test_a_folder_over_the_file_limit_is_413(client: TestClient, api_settings, root: Path) -> None:
    api_settings.max_import_files = 2
    answer = start(client, new_flight(client), path="route_17/frames")
    assert answer["http"] == 413 and "more than 2 photos" in answer["detail"]


def test_a_folder_on_another_file_system_is_copied(client: TestClient, api_settings, root: Path) -> None:
    shm = Path("/dev/shm")
    if not shm.is_dir() or shm.stat().st_dev == api_settings.data_dir.stat().st_dev:
        pytest.skip("no second file system (/dev/shm) to import from here")
    other = Path(tempfile.mkdtemp(dir=shm))
    try:
        shutil.copytree(root / "route_17" / "frames", other / "frames")
        api_settings.import_dirs = [root, other]
        flight = new_flight(client)
        record = finished(client, flight, start(client, flight, root=1, path="frames")["id"])
        sizes = sum(p.stat().st_size for p in (other / "frames").glob("*.tif"))
        assert record["imported"] == 3 and record["bytes_copied"] == sizes
    finally:
        shutil.rmtree(other)


def test_imports_are_their_owners_and_need_a_token(client: TestClient, root: Path) -> None:
    alice = user_headers(client, "alice")
    flight = new_flight(client, alice)
    other = client.post(
        f"/api/flights/{flight}/imports", json={"path": "route_17/frames"}, headers=user_headers(client, "bob")
    )
    assert other.status_code == 404
    anonymous = client.post(
        f"/api/flights/{flight}/imports", json={"path": "route_17/frames"}, headers={"Authorization": ""}
    )
    assert anonymous.status_code == 401
    mine = client.post(f"/api/flights/{flight}/imports", json={"path": "route_17/frames"}, headers=alice)
    assert mine.status_code == 202
    assert (
        client.get(
            f"/api/flights/{flight}/imports/{mine.json()['id']}", headers=user_headers(client, "carol")
        ).status_code
        == 404
    )


class HeldRunner(folder_import.ImportRunner):
    """Records what it is given instead of running it, so a test can run it when it likes."""

    def __init__(self) -> None:
        self.plans: list[tuple[int, folder_import.ImportPlan]] = []

    def submit(self, import_id: int, plan: folder_import.ImportPlan) -> None:
        self.plans.append((import_id, plan))


def test_a_cancelled_import_stops_and_a_silent_one_reads_interrupted(
    client: TestClient, api_settings, root: Path
) -> None:
    db: Database = client.app.state.db  # type: ignore[attr-defined]
    flight, runner = new_flight(client), HeldRunner()
    record = folder_import.start_import(db, api_settings, runner, flight, None, ImportCreate(path="route_17/frames"))
    again = start(client, flight, path="route_17/frames")
    assert again["http"] == 409 and f"import {record.id} of this flight is still running" in again["detail"]
    cancelled = client.post(f"/api/flights/{flight}/imports/{record.id}/cancel")
    assert cancelled.status_code == 200 and cancelled.json()["status"] == "cancelled"
    assert client.post(f"/api/flights/{flight}/imports/{record.id}/cancel").status_code == 409
    status, _ = folder_import.run_import(db, api_settings, record.id, runner.plans[0][1], threading.Event())
    assert status == "cancelled" and client.get(f"/api/flights/{flight}").json()["images"] == []
    # one whose process stopped stamping it reads as interrupted, and the folder may be imported again
    second = folder_import.start_import(db, api_settings, runner, flight, None, ImportCreate(path="route_17/frames"))
    with db.session() as s:
        old = utcnow() - timedelta(seconds=api_settings.stale_seconds + 1)
        s.execute(update(FolderImport).where(FolderImport.id == second.id).values(updated_at=old))
    seen = client.get(f"/api/flights/{flight}/imports/{second.id}").json()
    assert seen["status"] == "interrupted" and "POST the folder again" in seen["error"]
    third = start(client, flight, path="route_17/frames")
    assert third["http"] == 202 and finished(client, flight, third["id"])["imported"] == 3
