"""The tile cache and the shared COG readers: ETag and 304, no stale tile after a COG is rewritten, the cache's
bound, and tiles read by many threads at once equal to a plain rio-tiler read of the same COG.

The mosaic is a small georeferenced COG (UTM 30N, 3 cm/px) written by the service's own writer into the
workspace of a job made through the API, in two colours so that a rewrite is visible in the tiles.
"""

from __future__ import annotations

import random
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import morecantile
import numpy as np
import pytest
from fastapi.testclient import TestClient
from rasterio.windows import Window
from rio_tiler.io import Reader

from api.tiler import PNG_OPTIONS, TILE_SIZE, CogIdentity, TileCache, TileNotFoundError, Tiler
from core.db import Database, Job
from core.kinds import JobStatus
from tests.api.test_jobs import flight_with
from tests.scenes import make_flight
from workers.raster_io import open_block_writer, translate_to_cog
from workers.workspace import job_workspace

WIDTH, HEIGHT = 700, 500  # px: a few tiles at the finest zoom, overviews below


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return make_flight(tmp_path_factory.mktemp("frames"), n_frames=2, frame_size=(400, 300), seed=4).paths


def write_mosaic(path: Path, colour: tuple[int, int, int], scratch: Path) -> None:
    """A COG of vertical stripes tinted ``colour``, with a transparent band along its right edge."""
    cols = np.arange(WIDTH)
    stripes = ((cols // 16) % 2 * 80 + 60).astype(np.uint8)
    rgb = np.empty((HEIGHT, WIDTH, 3), np.uint8)
    for band, tint in enumerate(colour):
        rgb[..., band] = np.minimum(255, stripes.astype(int) + tint)[None, :]
    mask = np.broadcast_to(cols < WIDTH - 40, (HEIGHT, WIDTH))
    transform = [0.03, 0.0, 699_000.0, 0.0, -0.03, 5_630_000.0]
    with open_block_writer(scratch, WIDTH, HEIGHT, 32630, transform) as write:
        write(Window(0, 0, WIDTH, HEIGHT), rgb, mask)
    translate_to_cog(scratch, path, "deflate")


def set_status(api_settings, job_id: int, status: JobStatus) -> None:
    with Database(api_settings.resolved_database_url()).session() as s:
        s.get(Job, job_id).status = status


@pytest.fixture
def mosaic(client: TestClient, api_settings, frames: list[Path], tmp_path: Path) -> dict:
    """A succeeded mosaic job of the client's user, its COG path and the tiles of its finest zoom."""
    job = client.post("/api/jobs", json={"flight_id": flight_with(client, frames), "kind": "mosaic"}).json()
    path = job_workspace(api_settings.data_dir, job["id"]).mosaic_path()
    write_mosaic(path, (0, 0, 120), tmp_path / "scratch.tif")
    set_status(api_settings, job["id"], JobStatus.succeeded)
    tilejson = client.get(f"/tiles/{job['id']}/tilejson.json").json()
    west, south, east, north = tilejson["bounds"]
    tms, z = morecantile.tms.get("WebMercatorQuad"), tilejson["maxzoom"]
    ul, lr = tms.tile(west, north, z), tms.tile(east, south, z)
    with Reader(str(path)) as reader:  # rio-tiler's own test: the box's corners of a UTM raster are not in it
        tiles = [(z, x, y) for x in range(ul.x, lr.x + 1) for y in range(ul.y, lr.y + 1) if reader.tile_exists(x, y, z)]
    return {"id": job["id"], "path": path, "tiles": tiles, "tmp": tmp_path}


def url(job_id: int, tile: tuple[int, int, int]) -> str:
    z, x, y = tile
    return f"/tiles/{job_id}/{z}/{x}/{y}.png"


def plain_read(path: Path, tile: tuple[int, int, int]) -> bytes:
    """The tile as rio-tiler renders it from a fresh reader: no cache, no shared handle."""
    z, x, y = tile
    with Reader(str(path)) as reader:
        return bytes(reader.tile(x, y, z, tilesize=TILE_SIZE).render(img_format="PNG", **PNG_OPTIONS))


def tint(png: bytes) -> np.ndarray:
    """Mean (R, G, B) of the tile's opaque pixels."""
    bgra = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    opaque = bgra[..., 3] == 255
    assert opaque.any()
    return np.asarray(bgra[opaque][:, 2::-1].mean(axis=0))


def test_tiles_have_a_stable_strong_etag_and_are_revalidated_with_304(client: TestClient, mosaic: dict) -> None:
    first = client.get(url(mosaic["id"], mosaic["tiles"][0]))
    assert first.status_code == 200 and first.headers["content-type"] == "image/png"
    etag = first.headers["etag"]
    assert etag.startswith('"') and etag.endswith('"') and len(etag) > 10  # strong: no W/
    assert first.headers["cache-control"] == "private, max-age=3600"
    again = client.get(url(mosaic["id"], mosaic["tiles"][0]))
    assert again.headers["etag"] == etag and again.content == first.content
    other = client.get(url(mosaic["id"], mosaic["tiles"][1]))
    assert other.status_code == 200 and other.headers["etag"] != etag
    for header in (etag, f'"nope", {etag}', f"W/{etag}"):
        revalidated = client.get(url(mosaic["id"], mosaic["tiles"][0]), headers={"If-None-Match": header})
        assert revalidated.status_code == 304 and revalidated.content == b"", header
        assert revalidated.headers["etag"] == etag and revalidated.headers["cache-control"] == "private, max-age=3600"
    for header in ('"nope"', other.headers["etag"], "*"):
        full = client.get(url(mosaic["id"], mosaic["tiles"][0]), headers={"If-None-Match": header})
        assert full.status_code == 200 and full.content == first.content, header


def test_a_job_not_succeeded_has_its_tiles_revalidated_every_time(
    client: TestClient, api_settings, mosaic: dict
) -> None:
    set_status(api_settings, mosaic["id"], JobStatus.running)  # a retry may still rewrite the mosaic
    response = client.get(url(mosaic["id"], mosaic["tiles"][0]))
    assert response.status_code == 200 and response.headers["cache-control"] == "private, no-cache"
    assert "etag" in response.headers


def test_a_rewritten_cog_gives_new_tiles_and_a_new_etag(client: TestClient, api_settings, mosaic: dict) -> None:
    """A retried job rewrites its COG (temp file, then rename): the next request reads the new one, and the old
    ETag no longer answers 304."""
    tile = mosaic["tiles"][0]
    before = client.get(url(mosaic["id"], tile))
    red, _, blue = tint(before.content)
    assert blue > red + 60
    write_mosaic(mosaic["path"], (120, 0, 0), mosaic["tmp"] / "scratch2.tif")  # red-tinted, same size
    after = client.get(url(mosaic["id"], tile), headers={"If-None-Match": before.headers["etag"]})
    assert after.status_code == 200 and after.headers["etag"] != before.headers["etag"]
    red, _, blue = tint(after.content)
    assert red > blue + 60  # the new colour, not the cached tile
    assert after.content == plain_read(mosaic["path"], tile)
    tiler = client.app.state.tiler
    assert len(tiler.readers) == 1  # the old version's handles were closed, not kept beside the new ones


def test_tiles_equal_a_plain_rio_tiler_read_whether_cached_or_not(client: TestClient, mosaic: dict) -> None:
    expected = {tile: plain_read(mosaic["path"], tile) for tile in mosaic["tiles"]}
    for _ in range(2):  # rendered, then from the cache
        for tile in mosaic["tiles"]:
            assert client.get(url(mosaic["id"], tile)).content == expected[tile], tile
    uncached = Tiler(cache_bytes=0, max_cogs=0, readers_per_cog=1)
    identity = CogIdentity.of(mosaic["path"])
    assert all(uncached.tile(identity, *tile) == expected[tile] for tile in mosaic["tiles"])
    z, x, y = mosaic["tiles"][-1]
    assert client.get(url(mosaic["id"], (z, x + 3, y))).status_code == 404  # outside: cached as such, still 404
    response = client.get(url(mosaic["id"], (z, x + 3, y)))
    assert response.status_code == 404 and "is outside the mosaic of job" in response.json()["detail"]


def test_the_tile_cache_stays_within_its_bound(client: TestClient, mosaic: dict) -> None:
    sizes = [len(client.get(url(mosaic["id"], t)).content) for t in mosaic["tiles"]]
    bound = 2 * (max(sizes) + 200)  # room for two tiles
    client.app.state.tiler = tiler = Tiler(cache_bytes=bound, max_cogs=1, readers_per_cog=2)
    for tile in mosaic["tiles"]:
        assert client.get(url(mosaic["id"], tile)).status_code == 200
        assert tiler.tiles.bytes <= bound
    assert 2 <= len(tiler.tiles) < len(mosaic["tiles"])
    identity = CogIdentity.of(mosaic["path"])
    last, first = (identity, *mosaic["tiles"][-1]), (identity, *mosaic["tiles"][0])
    assert tiler.tiles.get(last) is not None and tiler.tiles.get(first) is None  # the oldest went first


def test_tile_cache_evicts_the_least_recently_used() -> None:
    identity = CogIdentity("a.tif", 1, 2, 3, 4)
    cache = TileCache(max_bytes=3 * (200 + 100))
    for x in range(3):
        cache.put((identity, 0, x, 0), bytes(100))
    assert cache.get((identity, 0, 0, 0)) == bytes(100)  # now the most recently used
    cache.put((identity, 0, 3, 0), bytes(100))
    assert cache.get((identity, 0, 1, 0)) is None and cache.get((identity, 0, 0, 0)) is not None
    assert cache.bytes == 3 * 300 and len(cache) == 3
    cache.put((identity, 0, 4, 0), bytes(10_000))  # larger than the whole cache: not kept, nothing evicted
    assert cache.get((identity, 0, 4, 0)) is None and len(cache) == 3
    assert TileCache(0).get((identity, 0, 0, 0)) is None


@pytest.mark.parametrize("cache_bytes", [0, 64 * 2**20], ids=["readers-only", "with-tile-cache"])
def test_tiles_read_by_many_threads_at_once_equal_a_fresh_read(mosaic: dict, cache_bytes: int) -> None:
    """16 threads on 2 shared handles of one COG (and on the tile cache): every tile equals a plain read."""
    tiles = mosaic["tiles"] + [(z - 1, x // 2, y // 2) for z, x, y in mosaic["tiles"]]
    expected = {tile: plain_read(mosaic["path"], tile) for tile in tiles}
    tiler = Tiler(cache_bytes=cache_bytes, max_cogs=4, readers_per_cog=2)
    identity = CogIdentity.of(mosaic["path"])
    order = tiles * 12
    random.Random(1).shuffle(order)
    with ThreadPoolExecutor(16) as pool:
        results = list(pool.map(lambda tile: tiler.tile(identity, *tile), order))
    assert [r == expected[t] for r, t in zip(results, order, strict=True)] == [True] * len(order)
    tiler.close()


def test_concurrent_requests_through_the_app_equal_a_fresh_read(client: TestClient, mosaic: dict) -> None:
    expected = {tile: plain_read(mosaic["path"], tile) for tile in mosaic["tiles"]}
    order = mosaic["tiles"] * 8
    random.Random(2).shuffle(order)
    with ThreadPoolExecutor(8) as pool:
        responses = list(pool.map(lambda tile: client.get(url(mosaic["id"], tile)), order))
    assert all(r.status_code == 200 and r.content == expected[t] for r, t in zip(responses, order, strict=True))


def test_tiles_off_the_grid_and_a_missing_cog(client: TestClient, api_settings, mosaic: dict) -> None:
    z, x, y = mosaic["tiles"][0]
    for path in (f"/tiles/{mosaic['id']}/27/0/0.png", f"/tiles/{mosaic['id']}/{z}/{2**z}/{y}.png"):
        response = client.get(path)
        assert response.status_code == 404 and "does not exist" in response.json()["detail"], path
    with pytest.raises(TileNotFoundError):
        Tiler(1000, 1, 1).tile(CogIdentity.of(mosaic["path"]), z, x + 5, y)  # east of the mosaic
    mosaic["path"].unlink()  # a retry that has removed the old mosaic and not written the new one yet
    response = client.get(url(mosaic["id"], mosaic["tiles"][0]))
    assert response.status_code == 409 and "has no mosaic yet" in response.json()["detail"]
