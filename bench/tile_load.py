"""Tiles under load: 50 map-viewer clients browsing a finished mosaic over a real uvicorn, on loopback only.

Run by hand from the repository root (never in CI)::

    .venv/bin/python bench/tile_load.py [--workers 1 2] [--clients 50] [--moves 6] [--json OUT]
    .venv/bin/python bench/tile_load.py --url http://127.0.0.1:8000 --job 3 --token T  # a server already up

The mosaic: one drone photo of ``../shared/data/drone_brighton_strip1`` (a seeded synthetic texture when it is
absent) repeated over a 6000 x 4500 px canvas at 3 cm/px in UTM 30N, with a footprint rotated by 12 degrees
so the edges are transparent as a real mosaic's are; written by the service's own writer
(``workers.raster_io``: tiled GeoTIFF, then a deflate COG with overviews and a mask) into a job workspace of a
fresh data dir, with a succeeded mosaic job record.

Each client is one keep-alive HTTP/1.1 connection (a browser opens up to 6 per host; one each keeps the
in-flight requests at ``--clients``) that browses as a map viewer does: a 1024 x 768 px view at a zoom
between the mosaic's maxzoom - 3 and maxzoom, then ``--moves`` pans (half a view) or zooms (one level),
requesting every tile of the view that lies in the mosaic's tile range, one after another, without pause
(closed loop: the harshest load for that number of clients). The client is a minimal asyncio HTTP client in
the bench process (cheaper than httpx, so it takes less of the CPU the server shares with it).

- **cold**: the first pass over the routes on a freshly started server (nothing open, nothing cached);
- **warm**: the same routes again, on the same connections (so with several workers each client's tiles are
  cached in the worker that served them).

Each configuration runs for every ``--workers`` value: the service as it is ("cached") and, as the reference
measured in the same run, the same service with both caches off (``FOTOSKHEMA_TILE_CACHE_BYTES=0``,
``FOTOSKHEMA_TILE_OPEN_COGS=0``: each tile opens its COG, as before the tile cache, though once instead of
twice). A pass stops after ``--max-seconds`` (the reference's cold pass at ~35 tiles/s would take minutes);
the figures then cover the requests that finished. Ratios are cached / reference (below 1.00: faster).

Authentication: the bench makes an admin user in its data dir with ``fotoskhema users create`` and sends its
token (``Authorization: Bearer``), as a script would; the viewer's signed tile URLs cost the same lookup.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import random
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PHOTO = ROOT.parent / "shared" / "data" / "drone_brighton_strip1" / "DJI_0024.JPG"
CANVAS = (6000, 4500)  # px, width x height
GSD_M = 0.03  # m per px
ORIGIN_UTM = (699_000.0, 5_630_000.0)  # upper-left corner, EPSG:32630 (Brighton)
VIEW_TILES = (4, 3)  # a 1024 x 768 px map view
REFERENCE_ENV = {"FOTOSKHEMA_TILE_CACHE_BYTES": "0", "FOTOSKHEMA_TILE_OPEN_COGS": "0"}


# -- The mosaic and its job -----------------------------------------------------------------------


def make_mosaic(data_dir: Path) -> int:
    """Write the bench mosaic as a succeeded mosaic job of a fresh data dir; return the job's id."""
    import numpy as np

    from core.db import Database, Flight, Job
    from core.kinds import JobKind, JobStatus
    from core.settings import Settings
    from workers.raster_io import open_block_writer, translate_to_cog
    from workers.workspace import job_workspace

    data_dir.mkdir(parents=True, exist_ok=True)
    db = Database(Settings(data_dir=data_dir).resolved_database_url())
    with db.session() as s:
        flight = Flight(name="tile bench")
        s.add(flight)
        s.flush()
        job = Job(flight_id=flight.id, kind=JobKind.mosaic, status=JobStatus.succeeded, stage="", progress=100.0)
        s.add(job)
        s.flush()
        job_id = int(job.id)
    ws = job_workspace(data_dir, job_id)
    ws.root.mkdir(parents=True, exist_ok=True)
    width, height = CANVAS
    photo = _photo()
    transform = [GSD_M, 0.0, ORIGIN_UTM[0], 0.0, -GSD_M, ORIGIN_UTM[1]]
    scratch = ws.root / "bench_scratch.tif"
    with open_block_writer(scratch, width, height, 32630, transform) as write:
        from rasterio.windows import Window

        for row in range(0, height, 512):
            for col in range(0, width, 512):
                h, w = min(512, height - row), min(512, width - col)
                rows, cols = np.mgrid[row : row + h, col : col + w]
                rgb = photo[rows % photo.shape[0], cols % photo.shape[1]]
                write(Window(col, row, w, h), rgb, _footprint(cols, rows, width, height))
    translate_to_cog(scratch, ws.mosaic_path(), "deflate")
    scratch.unlink()
    return job_id


def _photo() -> Any:
    import numpy as np

    if PHOTO.is_file():
        import cv2

        bgr = cv2.imread(str(PHOTO), cv2.IMREAD_COLOR)
        return np.ascontiguousarray(bgr[..., ::-1])
    rng = np.random.default_rng(7)  # a smooth seeded texture: compresses like a photo, not like noise
    coarse = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    return np.kron(coarse, np.ones((40, 40, 1), dtype=np.uint8))


def _footprint(cols: Any, rows: Any, width: int, height: int) -> Any:
    """True inside a rectangle of 85 % of the canvas rotated by 12 degrees about its centre."""
    angle = math.radians(12.0)
    u, v = cols - width / 2, rows - height / 2
    along, across = u * math.cos(angle) + v * math.sin(angle), -u * math.sin(angle) + v * math.cos(angle)
    return (abs(along) < 0.85 * width / 2) & (abs(across) < 0.85 * height / 2)


def make_token(data_dir: Path) -> str:
    """An admin token made with ``fotoskhema users create``."""
    env = {**os.environ, "FOTOSKHEMA_DATA_DIR": str(data_dir)}
    made = subprocess.run(
        [sys.executable, "-m", "api.cli", "users", "create", "bench", "--admin"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    return made.stdout.strip()


# -- The server -----------------------------------------------------------------------------------


def start_server(data_dir: Path, workers: int, port: int, extra_env: dict[str, str], log: Path) -> Any:
    from api.embedded_stack import wait_for_port

    env = {
        **os.environ,
        "FOTOSKHEMA_DATA_DIR": str(data_dir),
        "FOTOSKHEMA_DATABASE_URL": "",
        "FOTOSKHEMA_REDIS_URL": "redis://127.0.0.1:1/0",  # tiles need no broker
        **extra_env,
    }
    env.pop("DATABASE_URL", None)
    cmd = [sys.executable, "-m", "uvicorn", "api.main:create_app", "--factory", "--host", "127.0.0.1"]
    cmd += ["--port", str(port), "--workers", str(workers), "--no-access-log", "--log-level", "warning"]
    server = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log.open("wb"), stderr=subprocess.STDOUT)
    wait_for_port("127.0.0.1", port, 60, server)
    return server


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def stop_server(server: Any) -> None:
    from api.embedded_stack import stop

    stop([server])


# -- The clients ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Grid:
    """The mosaic's tiles: zoom range and, per zoom, the (x0, y0, x1, y1) tile range its bounds cover."""

    minzoom: int
    maxzoom: int
    ranges: dict[int, tuple[int, int, int, int]]


def tile_grid(tilejson: dict[str, Any]) -> Grid:
    import morecantile

    tms = morecantile.tms.get("WebMercatorQuad")
    west, south, east, north = tilejson["bounds"]
    ranges = {}
    for z in range(tilejson["minzoom"], tilejson["maxzoom"] + 1):
        ul, lr = tms.tile(west, north, z), tms.tile(east, south, z)
        ranges[z] = (ul.x, ul.y, lr.x, lr.y)
    return Grid(tilejson["minzoom"], tilejson["maxzoom"], ranges)


def browse(grid: Grid, rng: random.Random, moves: int) -> list[tuple[int, int, int]]:
    """The tiles one viewer asks for: a view, then ``moves`` pans or zooms, each view's tiles in order."""
    z = rng.randint(max(grid.minzoom, grid.maxzoom - 3), grid.maxzoom)
    x0, y0, x1, y1 = grid.ranges[z]
    cx, cy = rng.uniform(x0, x1 + 1), rng.uniform(y0, y1 + 1)  # view centre, in tiles of zoom z
    route: list[tuple[int, int, int]] = []
    for _ in range(moves + 1):
        route += view_tiles(grid, z, cx, cy)
        if rng.random() < 0.3:  # zoom in or out by one level about the view centre
            step = min(max(z + rng.choice((-1, 1)), grid.minzoom), grid.maxzoom) - z
            z, cx, cy = z + step, cx * 2**step, cy * 2**step
        else:
            cx += rng.choice((-1, 1)) * VIEW_TILES[0] / 2 * rng.random()
            cy += rng.choice((-1, 1)) * VIEW_TILES[1] / 2 * rng.random()
        x0, y0, x1, y1 = grid.ranges[z]
        cx, cy = min(max(cx, x0), x1 + 1), min(max(cy, y0), y1 + 1)  # the viewer keeps the mosaic in view
    return route


def view_tiles(grid: Grid, z: int, cx: float, cy: float) -> list[tuple[int, int, int]]:
    x0, y0, x1, y1 = grid.ranges[z]
    half_w, half_h = VIEW_TILES[0] / 2, VIEW_TILES[1] / 2
    xs = range(max(x0, math.floor(cx - half_w)), min(x1, math.floor(cx + half_w)) + 1)
    ys = range(max(y0, math.floor(cy - half_h)), min(y1, math.floor(cy + half_h)) + 1)
    return [(z, x, y) for y in ys for x in xs]


class Connection:
    """One keep-alive HTTP/1.1 connection; GETs whose answers carry a Content-Length (uvicorn's do)."""

    def __init__(self, host: str, port: int, token: str) -> None:
        self.host, self.port, self.token = host, port, token
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def get(self, path: str) -> tuple[int, int]:
        """(status, body bytes). A kept-alive connection the server has closed meanwhile (uvicorn closes idle
        ones after 5 s) is reopened once, as a browser does."""
        reused = self.writer is not None
        try:
            return await self._get(path)
        except (asyncio.IncompleteReadError, ConnectionError):
            await self.close()
            if not reused:
                raise
            return await self._get(path)

    async def _get(self, path: str) -> tuple[int, int]:
        if self.writer is None:
            self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        assert self.reader is not None
        self.writer.write(self.request(path))
        lines = (await self.reader.readuntil(b"\r\n\r\n")).decode("latin-1").split("\r\n")
        status = int(lines[0].split()[1])
        headers = {k.lower(): v for k, v in (line.split(": ", 1) for line in lines[1:] if ": " in line)}
        length = int(headers["content-length"])
        await self.reader.readexactly(length)
        if headers.get("connection", "").lower() == "close":
            await self.close()
        return status, length

    def request(self, path: str, close: bool = False) -> bytes:
        head = f"GET {path} HTTP/1.1\r\nHost: {self.host}\r\nAuthorization: Bearer {self.token}\r\n"
        return (head + ("Connection: close\r\n" if close else "") + "\r\n").encode()

    async def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


@dataclass
class Pass:
    latencies: list[float] = field(default_factory=list)  # s, of requests answered 200
    statuses: dict[int, int] = field(default_factory=dict)
    bytes: int = 0
    seconds: float = 0.0

    def summary(self) -> dict[str, Any]:
        ordered = sorted(self.latencies)

        def pct(q: float) -> float | None:
            return round(1000 * ordered[min(len(ordered) - 1, int(q * len(ordered)))], 1) if ordered else None

        return {
            "requests": sum(self.statuses.values()),
            "statuses": {str(k): v for k, v in sorted(self.statuses.items())},
            "p50_ms": pct(0.50),
            "p95_ms": pct(0.95),
            "p99_ms": pct(0.99),
            "req_per_s": round(sum(self.statuses.values()) / self.seconds, 1) if self.seconds else None,
            "mib": round(self.bytes / 2**20, 1),
        }


async def run_pass(connections: list[Connection], routes: list[list[str]], max_seconds: float) -> Pass:
    result = Pass()
    deadline = time.perf_counter() + max_seconds

    async def client(conn: Connection, route: list[str]) -> None:
        for path in route:
            if time.perf_counter() > deadline:
                return
            started = time.perf_counter()
            status, size = await conn.get(path)
            if status == 200:
                result.latencies.append(time.perf_counter() - started)
            result.statuses[status] = result.statuses.get(status, 0) + 1
            result.bytes += size

    started = time.perf_counter()
    await asyncio.gather(*(client(c, r) for c, r in zip(connections, routes, strict=True)))
    result.seconds = time.perf_counter() - started
    return result


async def measure(url: str, job_id: int, token: str, args: argparse.Namespace) -> dict[str, Any]:
    """Cold then warm pass of ``args.clients`` viewers over the job's tiles at ``url``."""
    parts = urlsplit(url)
    host, port = parts.hostname or "127.0.0.1", parts.port or 80
    probe = Connection(host, port, token)
    tilejson = await _get_json(probe, f"/tiles/{job_id}/tilejson.json")
    await probe.close()
    grid = tile_grid(tilejson)
    routes = [
        [f"/tiles/{job_id}/{z}/{x}/{y}.png" for z, x, y in browse(grid, random.Random(args.seed + i), args.moves)]
        for i in range(args.clients)
    ]
    connections = [Connection(host, port, token) for _ in range(args.clients)]
    cold = await run_pass(connections, routes, args.max_seconds)
    warm = await run_pass(connections, routes, args.max_seconds)
    for conn in connections:
        await conn.close()
    distinct = len({p for r in routes for p in r})
    return {
        "cold": cold.summary(),
        "warm": warm.summary(),
        "route_requests": sum(map(len, routes)),
        "distinct_tiles": distinct,
    }


async def _get_json(conn: Connection, path: str) -> dict[str, Any]:
    assert conn.writer is None
    reader, writer = await asyncio.open_connection(conn.host, conn.port)
    writer.write(conn.request(path, close=True))
    raw = await reader.read()
    writer.close()
    head, _, body = raw.partition(b"\r\n\r\n")
    if b" 200 " not in head.split(b"\r\n")[0]:
        raise SystemExit(f"GET {path}: {head.splitlines()[0].decode()} {body[:200].decode(errors='replace')}")
    return dict(json.loads(body))


# -- Main -----------------------------------------------------------------------------------------


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="uvicorn worker counts to run")
    parser.add_argument("--clients", type=int, default=50, help="concurrent viewers (connections)")
    parser.add_argument("--moves", type=int, default=6, help="pans or zooms per viewer after the first view")
    parser.add_argument("--max-seconds", type=float, default=30.0, help="cap on one pass")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-reference", action="store_true", help="skip the caches-off reference")
    parser.add_argument("--url", help="measure a server already running instead (no reference, no restart)")
    parser.add_argument("--job", type=int, help="with --url: the job whose mosaic to browse")
    parser.add_argument("--token", default="", help="with --url: the API token to send")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    if args.clients < 1 or args.moves < 0 or not 1 <= args.clients <= 1000:
        parser.error("--clients must be 1..1000 and --moves >= 0")
    if args.url:
        if args.job is None:
            parser.error("--url needs --job")
        if urlsplit(args.url).hostname not in ("127.0.0.1", "localhost", "::1"):
            parser.error("the bench runs on loopback only")
        results = {"external": asyncio.run(measure(args.url, args.job, args.token, args))}
    else:
        results = run_local(args)
    print_table(results, args)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


def run_local(args: argparse.Namespace) -> dict[str, Any]:
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="fotoskhema-tile-bench-") as tmp:
        data_dir = Path(tmp) / "data"
        started = time.perf_counter()
        job_id = make_mosaic(data_dir)
        token = make_token(data_dir)
        print(f"mosaic {CANVAS[0]} x {CANVAS[1]} px written in {time.perf_counter() - started:.1f} s", flush=True)
        configs = [("cached", {})] + ([] if args.no_reference else [("reference", REFERENCE_ENV)])
        for workers in args.workers:
            for name, env in configs:
                port = free_port()
                server = start_server(data_dir, workers, port, env, Path(tmp) / f"server-{name}-{workers}.log")
                try:
                    figures = asyncio.run(measure(f"http://127.0.0.1:{port}", job_id, token, args))
                finally:
                    stop_server(server)
                results[f"{name}/{workers}w"] = figures
                print(f"  {name}, {workers} worker(s): done", flush=True)
    return results


def print_table(results: dict[str, Any], args: argparse.Namespace) -> None:
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    print(f"\n{args.clients} clients, {args.moves} moves each; latency of 200 answers, ms; load average now {load}")
    header = f"{'run':<18}{'pass':<6}{'requests':>9}{'p50':>9}{'p95':>9}{'p99':>9}{'req/s':>9}  statuses"
    print(header)
    print("-" * len(header))
    for run, figures in results.items():
        for phase in ("cold", "warm"):
            f = figures[phase]
            print(
                f"{run:<18}{phase:<6}{f['requests']:>9}{_num(f['p50_ms'])}{_num(f['p95_ms'])}{_num(f['p99_ms'])}"
                f"{_num(f['req_per_s'])}  {f['statuses']}"
            )
    for workers in args.workers:
        ours, ref = results.get(f"cached/{workers}w"), results.get(f"reference/{workers}w")
        if not (ours and ref):
            continue
        for phase in ("cold", "warm"):
            a, b = ours[phase], ref[phase]
            ratio = {k: round(a[k] / b[k], 3) if a[k] and b[k] else None for k in ("p50_ms", "p95_ms", "req_per_s")}
            print(f"ratio cached/reference, {workers} worker(s), {phase}: {ratio}")


def _num(value: float | None) -> str:
    return f"{value:>9.1f}" if value is not None else f"{'-':>9}"


if __name__ == "__main__":
    raise SystemExit(main())
