"""Bounded requests: a body over its route's limit is refused while it streams (before it is spooled in full),
a file over the per-file limit is refused naming it with nothing left behind, photos are validated in bounded
memory, meshes are counted before they are parsed and parsed off the event loop.

Streaming is tested against a real uvicorn with raw sockets (a TestClient buffers the whole body first)."""

from __future__ import annotations

import asyncio
import io
import json
import os
import select
import socket
import struct
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from api.limits import MAX_JSON_BYTES, BodyLimits, _BodyMeter
from tests.conftest import REPO, _spawn, free_port
from tests.scenes import make_flight
from workers.algorithms.specimen import MeshFormatError, read_mesh
from workers.image_meta import ImageLimits, InvalidImageError, inspect_image

MIB = 1024 * 1024
PER_FILE = 2 * MIB  # the live server's limits
PER_REQUEST = 64 * MIB
SLACK = 16 * MIB  # what socket buffers hold between the client's send and the server's read
PARTS = 5


# -- a live server and raw HTTP ------------------------------------------------------------------------------


@dataclass
class Live:
    port: int
    pid: int
    data_dir: Path
    spool: Path  # the server's TMPDIR, where Starlette's SpooledTemporaryFile rolls over to disk
    token: str

    def open_spool_files(self) -> list[str]:
        """What the server process holds open in its temp folder (Python's temporary files there have no name
        in the folder: O_TMPFILE, or unlinked at once)."""
        found = []
        for fd in Path(f"/proc/{self.pid}/fd").iterdir():
            try:
                target = os.readlink(fd)
            except OSError:
                continue
            if target.startswith(str(self.spool)):
                found.append(target)
        return found


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Live]:
    from api.embedded_stack import stop, wait_for_port
    from core import accounts
    from core.db import Database
    from core.settings import Settings

    root = tmp_path_factory.mktemp("limits")
    data_dir, spool = root / "data", root / "spool"
    spool.mkdir()
    settings = Settings(data_dir=data_dir, database_url="")
    data_dir.mkdir()
    token = accounts.create_user(Database(settings.resolved_database_url()), "admin", admin=True)
    env = {
        **os.environ,
        "TMPDIR": str(spool),
        "FOTOSKHEMA_DATA_DIR": str(data_dir),
        "FOTOSKHEMA_DATABASE_URL": "",
        "FOTOSKHEMA_REDIS_URL": "redis://127.0.0.1:1/0",
        "FOTOSKHEMA_MAX_UPLOAD_BYTES": str(PER_FILE),
        "FOTOSKHEMA_MAX_REQUEST_BYTES": str(PER_REQUEST),
        "FOTOSKHEMA_MAX_FILES_PER_REQUEST": str(PARTS),
    }
    env.pop("DATABASE_URL", None)
    port = free_port()
    cmd = [sys.executable, "-m", "uvicorn", "api.main:create_app", "--factory", "--port", str(port)]
    server = _spawn(cmd, env, root / "api.log")
    try:
        wait_for_port("127.0.0.1", port, 60, server)
        yield Live(port, server.pid, data_dir, spool, token)
    finally:
        stop([server])


def new_flight(live: Live) -> int:
    headers = {"Authorization": f"Bearer {live.token}"}
    response = httpx.post(f"http://127.0.0.1:{live.port}/api/flights", json={"name": "f"}, headers=headers)
    assert response.status_code == 201, response.text
    return int(response.json()["id"])


@dataclass
class Answer:
    status: int
    body: dict
    sent: int  # bytes of the body sent before the answer came


def exchange(live: Live, method: str, path: str, headers: dict[str, str], pieces: Iterable[bytes]) -> Answer:
    """Send the request head, then body pieces until the server answers (or closes); read the answer."""
    sock = socket.create_connection(("127.0.0.1", live.port), timeout=30)
    head = {"Host": "127.0.0.1", "Authorization": f"Bearer {live.token}", **headers}
    sock.sendall(
        f"{method} {path} HTTP/1.1\r\n".encode() + "".join(f"{k}: {v}\r\n" for k, v in head.items()).encode() + b"\r\n"
    )
    sent, received = 0, b""
    try:
        for piece in pieces:
            if select.select([sock], [], [], 0)[0]:
                break
            sock.sendall(piece)
            sent += len(piece)
        while b"\r\n\r\n" not in received or len(received.split(b"\r\n\r\n", 1)[1]) < _length(received):
            chunk = sock.recv(65536)
            if not chunk:
                break
            received += chunk
    except (BrokenPipeError, ConnectionResetError):
        pass
    finally:
        sock.close()
    head_text, _, body = received.partition(b"\r\n\r\n")
    assert head_text, "no answer from the server"
    return Answer(int(head_text.split()[1]), json.loads(body[: _length(received)]), sent)


def _length(received: bytes) -> int:
    for line in received.split(b"\r\n\r\n", 1)[0].split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"content-length":
            return int(value)
    return 1 << 30


def chunked(pieces: Iterable[bytes]) -> Iterator[bytes]:
    for piece in pieces:
        yield f"{len(piece):x}\r\n".encode() + piece + b"\r\n"
    yield b"0\r\n\r\n"


BOUNDARY = "limitsboundary7MA4YWxk"


def part_head(field: str, filename: str | None) -> bytes:
    disposition = f'form-data; name="{field}"' + (f'; filename="{filename}"' if filename is not None else "")
    return f"--{BOUNDARY}\r\nContent-Disposition: {disposition}\r\nContent-Type: image/jpeg\r\n\r\n".encode()


def multipart(parts: list[tuple[str, str | None, bytes]]) -> bytes:
    body = b"".join(part_head(field, name) + data + b"\r\n" for field, name, data in parts)
    return body + f"--{BOUNDARY}--\r\n".encode()


MULTIPART = {"Content-Type": f"multipart/form-data; boundary={BOUNDARY}"}


# -- the live server: refused while streaming ----------------------------------------------------------------


def test_a_declared_length_over_the_cap_is_413_before_any_body_is_sent(live: Live) -> None:
    flight = new_flight(live)
    started = time.monotonic()
    answer = exchange(live, "POST", f"/api/flights/{flight}/images", {**MULTIPART, "Content-Length": str(2 << 30)}, [])
    assert answer.status == 413 and answer.sent == 0
    assert answer.body == {"detail": f"request body: {2 << 30} bytes; at most {PER_REQUEST} are accepted"}
    assert time.monotonic() - started < 5
    json_answer = exchange(
        live, "POST", "/api/flights", {"Content-Type": "application/json", "Content-Length": "600000000"}, []
    )
    assert json_answer.status == 413 and str(MAX_JSON_BYTES) in json_answer.body["detail"]


def test_a_chunked_body_over_the_cap_is_413_once_the_cap_is_passed(live: Live) -> None:
    endless = chunked(b"[" * 65536 for _ in range(10_000))  # 655 MB if it were read to the end
    answer = exchange(
        live, "POST", "/api/flights", {"Content-Type": "application/json", "Transfer-Encoding": "chunked"}, endless
    )
    assert answer.status == 413 and "larger than" in answer.body["detail"]
    assert answer.sent < MAX_JSON_BYTES + SLACK
    flight = new_flight(live)
    photos = chunked(part_head("files", f"p{k}.jpg") + b"x" * (PER_FILE // 2) + b"\r\n" for k in range(200))
    answer = exchange(
        live, "POST", f"/api/flights/{flight}/images", {**MULTIPART, "Transfer-Encoding": "chunked"}, photos
    )
    assert answer.status == 413 and answer.sent < PER_REQUEST + SLACK  # each file under its limit, the request over


def test_a_file_over_the_per_file_limit_is_413_naming_it_and_nothing_is_left(live: Live) -> None:
    flight = new_flight(live)
    small = make_flight(live.spool.parent / "frames", n_frames=1, frame_size=(64, 48), seed=1).paths[0].read_bytes()
    spooled_once = []

    def pieces() -> Iterator[bytes]:
        yield part_head("files", "good.jpg") + small + b"\r\n" + part_head("files", "../huge \u00e9.jpg")
        for k in range(960):  # 60 MiB of file; the limit is 2 MiB
            yield b"\xff" * 65536
            if k == 24:  # 1.6 MiB in: Starlette has rolled this file over to a temporary file on disk
                spooled_once.append(_wait_for(live.open_spool_files))

    answer = exchange(
        live, "POST", f"/api/flights/{flight}/images", {**MULTIPART, "Content-Length": str(PER_REQUEST - 1)}, pieces()
    )
    assert answer.status == 413
    assert answer.body == {"detail": f"huge \u00e9.jpg: file is larger than {PER_FILE} bytes"}
    assert answer.sent < PER_FILE + SLACK  # refused as the file passed its limit, not at the end of the body
    assert spooled_once == [True]  # the check below sees spooled files: it can fail
    assert not _wait_for(live.open_spool_files, timeout=0.5) and list(live.spool.iterdir()) == []
    folder = live.data_dir / "flights" / str(flight)
    assert not folder.exists() or [p for p in folder.rglob("*") if p.is_file()] == []
    listed = httpx.get(
        f"http://127.0.0.1:{live.port}/api/flights/{flight}", headers={"Authorization": f"Bearer {live.token}"}
    )
    assert listed.json()["image_count"] == 0


def test_too_many_parts_are_413(live: Live) -> None:
    flight = new_flight(live)
    body = multipart([("files", f"{k}.jpg", b"x") for k in range(PARTS + 1)])
    answer = exchange(
        live, "POST", f"/api/flights/{flight}/images", {**MULTIPART, "Content-Length": str(len(body))}, [body]
    )
    assert (
        answer.status == 413 and answer.body["detail"] == f"more than {PARTS} parts (files and fields) in one request"
    )


def _wait_for(probe, timeout: float = 5.0) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if probe():
            return True
        time.sleep(0.02)
    return bool(probe())


# -- the meter, a part's boundary split across chunks -------------------------------------------------------


@pytest.mark.parametrize("chunk", [1, 3, 7, 25, 64, 1000])
def test_the_meter_finds_every_part_whatever_the_chunk_edges(chunk: int) -> None:
    limits = BodyLimits(request_bytes=10_000, parts=4, file_bytes=100)
    tricky = b"\r\n--" + BOUNDARY[:-1].encode() + b"Z" * 20  # looks like a boundary almost to its end
    exact = tricky + b"y" * (100 - len(tricky))

    def feed(body: bytes) -> str | None:
        meter = _BodyMeter(limits, BOUNDARY.encode())
        problems = [meter.feed(body[k : k + chunk]) for k in range(0, len(body), chunk)]
        return next((p for p in problems if p), None)

    assert feed(multipart([("options", None, b"{}"), ("files", "a.jpg", exact), ("files", "b.jpg", exact)])) is None
    over = feed(multipart([("files", "a.jpg", exact), ("files", "dir/b.jpg", exact + b"!")]))
    assert over == "b.jpg: file is larger than 100 bytes"
    assert (
        feed(multipart([("files", f"{k}.jpg", b"x") for k in range(5)]))
        == "more than 4 parts (files and fields) in one request"
    )
    assert (
        feed(multipart([("options", None, b"1" * (MAX_JSON_BYTES + 1))])) == f"request body: larger than {10_000} bytes"
    )


# -- the TestClient (SQLite and PostgreSQL): the same limits, the handler never reached ----------------------


def test_upload_limits_through_the_app(client: TestClient) -> None:
    settings = client.app.state.settings  # type: ignore[attr-defined]  # the app's own, read on every request
    settings.max_upload_bytes = 1000
    settings.max_files_per_request = 3
    flight = client.post("/api/flights", json={"name": "f"}).json()["id"]
    response = client.post(f"/api/flights/{flight}/images", files=[("files", ("big.jpg", b"x" * 1001, "image/jpeg"))])
    assert response.status_code == 413 and response.json() == {"detail": "big.jpg: file is larger than 1000 bytes"}
    response = client.post(
        f"/api/flights/{flight}/images", files=[("files", (f"{k}.jpg", b"x", "image/jpeg")) for k in range(4)]
    )
    assert response.status_code == 413 and "more than 3 parts" in response.json()["detail"]
    folder = settings.data_dir / "flights" / str(flight)
    assert not folder.exists() or [p for p in folder.rglob("*") if p.is_file()] == []
    options = {"options": "[" * (MAX_JSON_BYTES + 1)}
    response = client.post("/api/calibrations", data=options, files=[("files", ("a.jpg", b"x", "image/jpeg"))])
    assert response.status_code == 413 and response.json() == {
        "detail": f"options: field is larger than {MAX_JSON_BYTES} bytes"
    }
    gcps = ("gcp_list.txt", b"1" * (5 * MIB + 1000), "text/plain")  # the request is under its cap, the file over
    response = client.put(f"/api/flights/{flight}/gcps", files={"file": gcps})
    assert response.status_code == 413 and "gcp_list.txt: file is larger than" in response.json()["detail"]


def test_a_mesh_over_its_limit_is_413_naming_it(client: TestClient) -> None:
    client.app.state.settings.max_mesh_bytes = 10_000  # type: ignore[attr-defined]
    model = ("panel.obj", b"v 0 0 0\n" * 2000, "text/plain")
    response = client.post("/api/crack-surveys", data={"options": "{}"}, files=[("model", model)])
    assert response.status_code == 413 and response.json() == {"detail": "panel.obj: file is larger than 10000 bytes"}


# -- photos validated in bounded memory ----------------------------------------------------------------------


def write_png(path: Path, width: int, height: int, rows: Iterable[bytes], interlace: bool = False) -> None:
    """An 8-bit RGB PNG from its filtered rows (filter byte included), compressed as they come."""
    pack = zlib.compressobj(6)
    with path.open("wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n")
        _png_chunk(f, b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, int(interlace)))
        data = b"".join(pack.compress(row) for row in rows) + pack.flush()
        for k in range(0, len(data), 1 << 16):
            _png_chunk(f, b"IDAT", data[k : k + (1 << 16)])
        _png_chunk(f, b"IEND", b"")


def _png_chunk(f: io.BufferedWriter, kind: bytes, data: bytes) -> None:
    f.write(struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(data, zlib.crc32(kind))))


PEAK_RSS = """
import resource, sys
from pathlib import Path
from workers.image_meta import inspect_image
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
meta = inspect_image(Path(sys.argv[1]))
print(meta["width"], meta["height"], (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) // 1024)
"""


def test_a_huge_png_is_validated_in_bounded_memory(tmp_path: Path) -> None:
    width, height = 15000, 16000  # 720 MB decoded; the file is a few MiB
    line = np.zeros(1 + 3 * width, np.uint8)
    line[1::291] = 200
    write_png(tmp_path / "huge.png", width, height, (line.tobytes() for _ in range(height)))
    assert (tmp_path / "huge.png").stat().st_size < 8 * MIB
    done = subprocess.run(
        [sys.executable, "-c", PEAK_RSS, str(tmp_path / "huge.png")],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    )
    w, h, growth_mib = (int(v) for v in done.stdout.split())
    assert (w, h) == (width, height)
    assert growth_mib < 100  # a full decode grows by ~700 MiB


def test_png_checks_match_a_full_decode(tmp_path: Path) -> None:
    """Interlaced and not, whole, cut short, or with a bad filter byte: refused exactly when Pillow's full
    decode fails, and the metadata the same."""
    rng = np.random.default_rng(4)
    pixels = rng.integers(0, 255, (37, 53, 3), dtype=np.uint8)
    for interlace in (False, True):
        path = tmp_path / f"i{int(interlace)}.png"
        write_png(path, 53, 37, _rows(pixels, interlace), interlace)
        data = path.read_bytes()
        variants = {"whole": data, **{f"cut{f}": data[: int(len(data) * f)] for f in (0.5, 0.9, 0.99)}}
        raw = b"".join(_rows(pixels, interlace))
        bad_filter = bytearray(raw)
        bad_filter[len(raw) // 2 - (len(raw) // 2) % (1 + 3 * 53 if not interlace else 1)] = 9
        write_png(tmp_path / "bad.png", 53, 37, [bytes(bad_filter)], interlace)
        variants["filter"] = (tmp_path / "bad.png").read_bytes()
        for name, content in variants.items():
            (tmp_path / "v.png").write_bytes(content)
            assert _pillow_decodes(tmp_path / "v.png") == _accepted(tmp_path / "v.png"), (interlace, name)
        assert inspect_image(path)["width"] == 53 and _pillow_decodes(path)


def _rows(pixels: np.ndarray, interlace: bool) -> Iterator[bytes]:
    passes = [(0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2)]
    for x0, y0, dx, dy in passes if interlace else [(0, 0, 1, 1)]:
        sub = pixels[y0::dy, x0::dx]
        for row in sub if sub.shape[1] else []:
            yield b"\x00" + row.tobytes()


def _pillow_decodes(path: Path) -> bool:
    try:
        with Image.open(path) as img:
            img.load()
    except (OSError, SyntaxError, ValueError):
        return False
    return True


def _accepted(path: Path) -> bool:
    try:
        inspect_image(path, ImageLimits(min_side=1))
    except InvalidImageError:
        return False
    return True


def test_a_jpeg_is_decoded_at_an_eighth_of_its_size(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A large JPEG is decoded at 1/8 of its size; a small one at the scale that keeps 512 px for the photo check
    (workers.photo_check), never whole unless it is that small."""
    from PIL import JpegImagePlugin

    decoded: list[tuple[int, int]] = []
    load = JpegImagePlugin.JpegImageFile.load

    def spy(self):  # type: ignore[no-untyped-def]
        decoded.append(self.size)
        return load(self)

    monkeypatch.setattr(JpegImagePlugin.JpegImageFile, "load", spy)
    for (w, h), seen in {(4800, 3600): (600, 450), (1600, 1200): (800, 600), (600, 400): (600, 400)}.items():
        Image.fromarray(np.full((h, w, 3), 90, np.uint8)).save(tmp_path / "a.jpg", quality=90)
        decoded.clear()
        meta = inspect_image(tmp_path / "a.jpg")
        assert (meta["width"], meta["height"]) == (w, h) and set(decoded) == {seen}  # load() runs again, a no-op
    (tmp_path / "cut.jpg").write_bytes((tmp_path / "a.jpg").read_bytes()[:-2000])
    with pytest.raises(InvalidImageError, match="truncated"):
        inspect_image(tmp_path / "cut.jpg")


# -- meshes: counted before parsing, parsed off the event loop ----------------------------------------------


def test_mesh_counts_are_checked_before_parsing(monkeypatch: pytest.MonkeyPatch) -> None:
    from workers.algorithms.specimen import mesh

    ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
    ply += b"property float z\nelement face 4000000000\nproperty list uchar int vertex_indices\nend_header\n"
    with pytest.raises(MeshFormatError, match="4000000000 faces; at most 2000000 triangles"):
        read_mesh(ply + b"\0" * 64, "big.ply")
    monkeypatch.setattr(mesh, "MAX_TRIANGLES", 10)
    monkeypatch.setattr(mesh, "_read_obj", lambda data: pytest.fail("parsed although over the limit"))
    obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * 11
    with pytest.raises(MeshFormatError, match="11 faces; at most 10 triangles"):
        read_mesh(obj, "many.obj")


def test_a_mesh_error_does_not_echo_the_file() -> None:
    with pytest.raises(MeshFormatError) as refused:
        read_mesh(b"v 1 2 " + b"9e" * 50_000 + b"\nf 1 1 1\n", "long.obj")
    assert len(str(refused.value)) < 400


def test_a_mesh_is_parsed_in_a_worker_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    from fastapi import UploadFile

    from api import crack_survey_service
    from api.errors import InvalidInputError

    seen: list[tuple[bool, bool]] = []

    def spy(data: bytes, name: str):  # type: ignore[no-untyped-def]
        try:
            asyncio.get_running_loop()
            on_loop = True
        except RuntimeError:
            on_loop = False
        seen.append((on_loop, threading.current_thread() is threading.main_thread()))
        raise MeshFormatError(f"{name}: stop here")

    monkeypatch.setattr(crack_survey_service, "read_mesh", spy)
    config = {"specimen": {"mesh": "m.obj", "plane": None}, "mm_per_px": 1.0, "stages": []}
    model = UploadFile(io.BytesIO(b"v 0 0 0\n"), filename="m.obj")
    with pytest.raises(InvalidInputError, match="stop here"):
        asyncio.run(crack_survey_service._mesh_attachment(config, model, 1000))
    assert seen == [(False, False)]  # no event loop in the parsing thread, and not the loop's thread


def test_full_decodes_share_a_memory_budget(tmp_path: Path) -> None:
    """A full decode (a format without a bounded reader) holds the process's budget: two decodes that together
    exceed it take turns; a TIFF is decoded block by block and needs none of it."""
    from workers.image_meta import DecodeBudget

    budget, inside, most = DecodeBudget(100), [0], [0]
    lock = threading.Lock()

    def decode() -> None:
        with budget.hold(80):
            with lock:
                inside[0] += 1
                most[0] = max(most[0], inside[0])
            time.sleep(0.05)
            with lock:
                inside[0] -= 1

    threads = [threading.Thread(target=decode) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert most == [1] and budget.free == 100
    with budget.hold(500):  # larger than the whole budget: it waits to be alone, then runs
        assert budget.free == 0
    Image.fromarray(np.zeros((40, 30, 3), np.uint8)).save(tmp_path / "a.tif")
    assert inspect_image(tmp_path / "a.tif", ImageLimits(decode_budget_bytes=10))["format"] == "TIFF"
