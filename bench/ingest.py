"""Getting a large frame in: resumable (tus) upload and server-side import against a multipart upload of the
same file, over a real uvicorn on loopback.

Run by hand from the repository root (never in CI)::

    .venv/bin/python bench/ingest.py [--size-mb 300] [--chunk-mb 32] [--json OUT]

The frame: an uncompressed tiled RGB TIFF of about ``--size-mb`` (the worst case for the photo check, which
decodes every tile). Each way runs against a freshly started API (``tests.live_api``: uvicorn alone over
SQLite, per-file limit raised to 8 GiB, pixels to 1 Gpx) and is timed from the first request until the photo is stored:

- **multipart** (the reference): ``POST /api/flights/{id}/images`` with the file, streamed (``http.client``);
- **tus**: ``POST /api/flights/{id}/uploads``, then PATCHes of ``--chunk-mb`` with their SHA-256, as the
  viewer sends them (the hashing in the client is timed too);
- **import (link)**: ``POST /api/flights/{id}/imports`` of a folder on the data dir's file system (hard link);
- **import (copy)**: the same from a folder on another file system (``/dev/shm``), when there is one.

For each: seconds, MB/s, the API process's peak RSS (VmHWM) and how much it grew over the idle process
(bounded memory: the upload ways must not grow with the file), and the new disk the data dir holds afterwards
(the import by hard link holds none of the frame's bytes). GDAL's block cache is set to 64 MB in every API (its
default, 5 % of RAM, keeps up to the whole decoded frame after the photo check, whichever way it came).
Ratios are this way / multipart.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import http.client
import itertools
import json
import math
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.live_api import ApiProcess, api_process  # noqa: E402

LIMIT = str(8 * 1024**3)
# GDAL's block cache (5 % of RAM by default) keeps what the photo check decodes: bounded here for every way alike,
# so that what an upload way itself holds shows in the API's RSS
GDAL_CACHE_MB = "64"


def write_frame(path: Path, size_mb: int) -> int:
    """An uncompressed tiled RGB TIFF of about ``size_mb`` MB (noise tiles); its size in bytes."""
    import rasterio
    from rasterio.windows import Window

    side = int(math.sqrt(size_mb * 1e6 / 3)) // 256 * 256
    tile = np.random.default_rng(0).integers(0, 256, (3, 256, 256), dtype=np.uint8)
    profile = {"driver": "GTiff", "width": side, "height": side, "count": 3, "dtype": "uint8", "tiled": True}
    with rasterio.open(path, "w", **profile, blockxsize=256, blockysize=256) as dst:
        for row in range(0, side, 256):
            for col in range(0, side, 256):
                dst.write(np.roll(tile, row + col, axis=2), window=Window(col, row, 256, 256))
    return path.stat().st_size


def peak_rss_mb(server: ApiProcess) -> float:
    assert server.process is not None
    for line in Path(f"/proc/{server.process.pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def disk_mb(folder: Path) -> float:
    """Disk held by ``folder``'s files alone: a file hard-linked from elsewhere (nlink > 1) costs nothing more."""
    total = 0
    for p in folder.rglob("*"):
        if p.is_file() and (st := p.stat()).st_nlink == 1:
            total += st.st_blocks * 512
    return total / 1e6


def send(
    server: str, token: str, method: str, path: str, body: Any, headers: dict[str, str]
) -> tuple[int, bytes, dict]:
    """One request with the standard library's client, which sends a large body at loopback speed (httpx's
    sync client sends a 300 MB body at about 13 MB/s here, which would hide the server)."""
    host, port = server.removeprefix("http://").split(":")
    conn = http.client.HTTPConnection(host, int(port), timeout=600)
    try:
        conn.request(method, path, body=body, headers={"Authorization": f"Bearer {token}", **headers})
        answer = conn.getresponse()
        return answer.status, answer.read(), {k.lower(): v for k, v in answer.getheaders()}
    finally:
        conn.close()


def by_multipart(server: ApiProcess, flight: int, frame: Path, _: dict[str, Any]) -> None:
    boundary = "fotoskhemabench"
    head = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="files"; filename="{frame.name}"\r\n'
        "Content-Type: image/tiff\r\n\r\n"
    ).encode()
    tail = f"\r\n--{boundary}--\r\n".encode()
    with frame.open("rb") as f:
        body = itertools.chain([head], iter(lambda: f.read(1 << 20), b""), [tail])
        headers = {
            "Content-Type": f"multipart/form-data; boundary={boundary}",
            "Content-Length": str(len(head) + frame.stat().st_size + len(tail)),
        }
        status, text, _ = send(server.url, server.token, "POST", f"/api/flights/{flight}/images", body, headers)
    assert status == 201, text


def by_tus(server: ApiProcess, flight: int, frame: Path, opts: dict[str, Any]) -> None:
    size, chunk = frame.stat().st_size, opts["chunk_mb"] * 1024 * 1024
    tus = {"Tus-Resumable": "1.0.0"}
    meta = f"filename {base64.b64encode(frame.name.encode()).decode()}"
    headers = {**tus, "Upload-Length": str(size), "Upload-Metadata": meta}
    status, text, answer = send(server.url, server.token, "POST", f"/api/flights/{flight}/uploads", b"", headers)
    assert status == 201, text
    url, offset = answer["location"], 0
    with frame.open("rb") as f:
        while data := f.read(chunk):
            digest = base64.b64encode(hashlib.sha256(data).digest()).decode()
            headers = {**tus, "Content-Type": "application/offset+octet-stream", "Upload-Offset": str(offset)}
            headers["Upload-Checksum"] = f"sha256 {digest}"
            status, text, _ = send(server.url, server.token, "PATCH", url, data, headers)
            assert status == 204, text
            offset += len(data)


def by_import(server: ApiProcess, flight: int, frame: Path, opts: dict[str, Any]) -> None:
    client = httpx.Client(base_url=server.url, headers={"Authorization": f"Bearer {server.token}"})
    answer = client.post(f"/api/flights/{flight}/imports", json={"root": 0, "path": "route"})
    assert answer.status_code == 202, answer.text
    while (record := client.get(f"/api/flights/{flight}/imports/{answer.json()['id']}").json())["status"] == "running":
        time.sleep(0.05)
    assert record["imported"] == 1, record
    opts["bytes_copied"] = record["bytes_copied"]


def run(name: str, how: Callable[..., None], frame: Path, work: Path, opts: dict[str, Any], **settings: str) -> dict:
    limits = {"max_upload_bytes": LIMIT, "max_request_bytes": LIMIT, "max_image_pixels": str(10**9)}
    server = api_process(work / name / "data", **limits, **settings)
    server.env["GDAL_CACHEMAX"] = GDAL_CACHE_MB
    server.start()
    try:
        time.sleep(1.0)
        idle = peak_rss_mb(server)
        with httpx.Client(base_url=server.url, headers={"Authorization": f"Bearer {server.token}"}, timeout=600) as c:
            flight = c.post("/api/flights", json={"name": name}).json()["id"]
            start = time.perf_counter()
            how(server, flight, frame, opts)
            seconds = time.perf_counter() - start
        peak = peak_rss_mb(server)
    finally:
        server.kill()
    size_mb = frame.stat().st_size / 1e6
    return {
        "way": name,
        "seconds": seconds,
        "mb_per_s": size_mb / seconds,
        "peak_rss_mb": peak,
        "rss_growth_mb": peak - idle,
        "data_dir_mb": disk_mb(work / name / "data"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size-mb", type=int, default=300)
    parser.add_argument("--chunk-mb", type=int, default=32)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="fotoskhema-ingest-"))
    try:
        route = work / "import" / "route"
        route.mkdir(parents=True)
        frame = route / "strip_000.tif"
        print(f"frame: {write_frame(frame, args.size_mb) / 1e6:.0f} MB uncompressed tiled TIFF")
        opts = {"chunk_mb": args.chunk_mb}
        rows = [
            run("multipart", by_multipart, frame, work, opts),
            run("tus", by_tus, frame, work, opts),
            run("import (link)", by_import, frame, work, opts, import_dirs=json.dumps([str(work / "import")])),
        ]
        shm = Path("/dev/shm")
        if shm.is_dir() and shm.stat().st_dev != work.stat().st_dev:
            other = Path(tempfile.mkdtemp(dir=shm))
            try:
                shutil.copytree(work / "import", other / "import")
                dirs = json.dumps([str(other / "import")])
                rows.append(
                    run(
                        "import (copy)",
                        by_import,
                        other / "import" / "route" / frame.name,
                        work,
                        opts,
                        import_dirs=dirs,
                    )
                )
            finally:
                shutil.rmtree(other)
        reference = rows[0]["seconds"]
        columns = ("s", "MB/s", "vs multipart", "API peak RSS MB", "RSS growth MB", "new disk MB")
        print(f"{'way':<15} " + " ".join(f"{c:>{w}}" for c, w in zip(columns, (7, 7, 12, 16, 14, 12), strict=True)))
        for r in rows:
            r["ratio"] = r["seconds"] / reference
            print(
                f"{r['way']:<15} {r['seconds']:7.2f} {r['mb_per_s']:7.0f} {r['ratio']:12.2f} "
                f"{r['peak_rss_mb']:16.0f} {r['rss_growth_mb']:14.0f} {r['data_dir_mb']:12.0f}"
            )
        if args.json:
            args.json.write_text(json.dumps(rows, indent=2))
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
