"""Reading tiles of a job's COGs under load: each COG opened once per process, rendered tiles kept in memory.

A COG is known by its identity (:class:`CogIdentity`: path, device, inode, size and mtime in ns), taken from one
``stat`` per request. A job that is retried rewrites its COG (temp file, then ``os.replace``: a new inode), so
the next request sees a new identity: the old readers are closed and the old tiles are never answered again
(they age out of the cache). Nothing is cached by job id or path alone.

Thread safety: the tile routes are sync FastAPI handlers, run on a thread pool, and a GDAL dataset handle must
not be used by two threads at once. Each open COG is therefore a small pool of handles (:class:`_ReaderPool`),
each lent to one thread at a time; a thread that finds them all busy waits for one. Measured on the shared
2-core machine (8 threads rendering 240 distinct tiles of bench/tile_load.py's mosaic, tiles/s, best / median of
5 rounds, other jobs running): a new handle per tile, opened twice as before 57 / 48; one handle behind a lock
49 / 47; a pool of 2 handles 87 / 42; of 4 handles 74 / 43; one handle per thread 65 / 44; all byte-identical to
sequential fresh reads. Rendering is CPU-bound, so on 2 cores no way of sharing handles wins by much; a pool is
as fast as a handle per thread while bounding the open files (the thread pool has 40 threads), and its size is
a setting. What pays is not rendering twice: the tile cache, one renderer per tile at a time, and PNG deflate
level 1 (encoding was two thirds of a tile's time).

Rendered tiles (PNG bytes, or "outside the raster") are kept in an LRU bounded by bytes (:class:`TileCache`),
keyed by (identity, z, x, y). A tile's ETag is a hash of the same key and of the rendering code's version, so
it is known before the tile is read: a revalidation with a matching ``If-None-Match`` costs one ``stat``.
"""

from __future__ import annotations

import hashlib
import math
import os
import threading
from collections import OrderedDict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import rio_tiler
from morecantile import Tile
from pyproj import Transformer
from rio_tiler.constants import WGS84_CRS
from rio_tiler.errors import TileOutsideBounds
from rio_tiler.io import ImageReader, Reader
from rio_tiler.models import ImageData

TILE_SIZE = 256
MAX_ZOOM = 26
# Part of every ETag: a change to how tiles are rendered (rio-tiler, tile size, this module) changes the bytes,
# so it must change the tags browsers hold. Bump RENDER_VERSION when the rendering below changes.
RENDER_VERSION = 1
_ETAG_SALT = f"fotoskhema-tile/{RENDER_VERSION}/{rio_tiler.__version__}/{TILE_SIZE}"
# PNG deflate level: 1 encodes a 256 px aerial tile in ~5 ms instead of ~16 ms at GDAL's default 6, for ~7 % more
# bytes; encoding was two thirds of an uncached tile's time.
PNG_OPTIONS: dict[str, Any] = {"ZLEVEL": 1}
_ENTRY_OVERHEAD = 200  # bytes charged per cached tile besides its PNG: key, node and bookkeeping


class TileNotFoundError(LookupError):
    """The tile does not exist in the tile grid (``off_grid``) or lies outside the raster's bounds."""

    def __init__(self, off_grid: bool) -> None:
        super().__init__("off the tile grid" if off_grid else "outside the raster")
        self.off_grid = off_grid


@dataclass(frozen=True)
class CogIdentity:
    """One version of a COG file: a rewrite (new inode, size or mtime) is a new identity."""

    path: str
    device: int
    inode: int
    size: int
    mtime_ns: int

    @classmethod
    def of(cls, path: Path) -> CogIdentity:
        """The identity of the file at ``path`` now; ``FileNotFoundError`` when it is gone."""
        st = os.stat(path)
        return cls(str(path), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)

    def tile_etag(self, z: int, x: int, y: int) -> str:
        """A strong ETag of tile z/x/y of this version (a hash: it names no server path)."""
        key = f"{_ETAG_SALT}|{self.path}|{self.device}|{self.inode}|{self.size}|{self.mtime_ns}|{z}/{x}/{y}"
        return '"' + hashlib.blake2b(key.encode(), digest_size=16).hexdigest() + '"'


@dataclass(frozen=True)
class CogInfo:
    """What a TileJSON says of a COG: its bounds (lon/lat, or pixels with y negated) and zoom range."""

    georeferenced: bool
    bounds: tuple[float, float, float, float]  # west, south, east, north
    minzoom: int
    maxzoom: int


# -- One open COG ---------------------------------------------------------------------------------


class _OpenCog:
    """A rasterio handle and rio-tiler's reader over it: on the Earth for a geographic or projected CRS, in
    the local pixel grid otherwise (no CRS, or a specimen's local engineering CRS in mm)."""

    def __init__(self, path: str) -> None:
        self.dataset = rasterio.open(path)
        try:
            crs = self.dataset.crs
            mapped = crs is not None and (crs.is_geographic or crs.is_projected)
            self.reader: Reader = (
                Reader(path, dataset=self.dataset) if mapped else ImageReader(path, dataset=self.dataset)
            )
        except Exception:
            self.dataset.close()
            raise

    def close(self) -> None:
        self.reader.close()
        self.dataset.close()  # a dataset handed to rio-tiler is not closed by it

    def info(self) -> CogInfo:
        reader = self.reader
        if reader.crs is not None:
            west, south, east, north = reader.get_geographic_bounds(WGS84_CRS)
        else:  # pixel plane, y pointing down as rows do: Leaflet's CRS.Simple shows it with y negated
            west, south, east, north = 0.0, -float(self.dataset.height), float(self.dataset.width), 0.0
        return CogInfo(reader.crs is not None, (west, south, east, north), int(reader.minzoom), int(reader.maxzoom))

    def render(self, z: int, x: int, y: int) -> bytes:
        """PNG of tile z/x/y; :class:`TileNotFoundError` outside the raster."""
        reader = self.reader
        georeferenced = reader.crs is not None
        # The local pixel grid of a raster without map coordinates has more than 2**z columns at a zoom level.
        if georeferenced and not (x < 2**z and y < 2**z):
            raise TileNotFoundError(off_grid=True)
        try:
            if not reader.tile_exists(x, y, z):
                raise TileOutsideBounds
            return bytes(reader.tile(x, y, z, tilesize=TILE_SIZE).render(img_format="PNG", **PNG_OPTIONS))
        except TileOutsideBounds:
            # A UTM mosaic is slightly rotated inside its lon/lat box, so rio-tiler calls tiles at the box's
            # corners outside; they are inside the advertised bounds: answer them empty, not 404.
            if georeferenced and self._meets_geographic_bounds(x, y, z):
                return empty_png()
            raise TileNotFoundError(off_grid=False) from None

    def _meets_geographic_bounds(self, x: int, y: int, z: int) -> bool:
        west, south, east, north = self.reader.get_geographic_bounds(WGS84_CRS)
        t_west, t_south, t_east, t_north = self.reader.tms.bounds(Tile(x, y, z))
        return bool(t_west < east and t_east > west and t_south < north and t_north > south)


def sample_dataset(dataset: Any, x: float, y: float, lonlat: bool) -> float | None:
    """``Tiler.sample`` on an open rasterio dataset."""
    if lonlat:
        if dataset.crs is None:
            return None
        gx, gy = lonlat_transformer(dataset.crs.to_wkt()).transform(x, y)
        if not (math.isfinite(gx) and math.isfinite(gy)):  # far outside a UTM zone, beyond its projection's reach
            return None
        row, col = dataset.index(gx, gy)
    else:
        col, row = int(np.floor(x)), int(np.floor(y))
    if not (0 <= row < dataset.height and 0 <= col < dataset.width):
        return None
    value = dataset.read(1, window=((row, row + 1), (col, col + 1)))[0, 0]
    nodata = dataset.nodata
    if not np.isfinite(value) or (nodata is not None and (value == nodata or (np.isnan(nodata) and np.isnan(value)))):
        return None
    return float(value)


@lru_cache(maxsize=16)
def lonlat_transformer(crs_wkt: str) -> Transformer:
    """lon/lat -> a raster's CRS, made once per CRS; infinite where the point is outside that projection's domain
    (GDAL's transform raises there instead)."""
    return Transformer.from_crs("EPSG:4326", crs_wkt, always_xy=True)


@lru_cache(maxsize=1)
def empty_png() -> bytes:
    """A fully transparent tile."""
    return bytes(
        ImageData(np.ma.masked_all((3, TILE_SIZE, TILE_SIZE), dtype="uint8")).render(img_format="PNG", **PNG_OPTIONS)
    )


class _ReaderPool:
    """Up to ``size`` open handles of one COG version, each lent to one thread at a time (a GDAL dataset is not
    thread-safe). Handles are opened on demand; after :meth:`close`, lent ones are closed when given back."""

    def __init__(self, path: str, size: int) -> None:
        self._path = path
        self._slots = threading.BoundedSemaphore(size)
        self._lock = threading.Lock()
        self._idle: list[_OpenCog] = []
        self._closed = False
        self.info: CogInfo | None = None  # filled by the first reader, constant for this version

    @contextmanager
    def borrow(self) -> Iterator[_OpenCog]:
        with self._slots:
            with self._lock:
                cog = self._idle.pop() if self._idle else None
            if cog is None:
                cog = _OpenCog(self._path)
            try:
                yield cog
            except BaseException:
                cog.close()  # a handle that failed mid-read is not lent again
                raise
            with self._lock:
                if not self._closed:
                    self._idle.append(cog)
                    return
            cog.close()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            idle, self._idle = self._idle, []
        for cog in idle:
            cog.close()


class ReaderCache:
    """At most ``max_cogs`` COG versions kept open (LRU), ``readers_per_cog`` handles each. A new version of a
    path closes the old one's handles at once (the replaced file's disk space is freed). ``max_cogs=0``: every
    request opens its COG and closes it after."""

    def __init__(self, max_cogs: int, readers_per_cog: int) -> None:
        self._max, self._per_cog = max_cogs, max(1, readers_per_cog)
        self._pools: OrderedDict[CogIdentity, _ReaderPool] = OrderedDict()
        self._by_path: dict[str, CogIdentity] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._pools)

    @contextmanager
    def borrow(self, identity: CogIdentity) -> Iterator[tuple[_OpenCog, _ReaderPool | None]]:
        if self._max == 0:
            cog = _OpenCog(identity.path)
            try:
                yield cog, None
            finally:
                cog.close()
            return
        pool = self._pool(identity)
        with pool.borrow() as cog:
            yield cog, pool

    def _pool(self, identity: CogIdentity) -> _ReaderPool:
        stale: list[_ReaderPool] = []
        with self._lock:
            pool = self._pools.get(identity)
            if pool is not None:
                self._pools.move_to_end(identity)
                return pool
            old = self._by_path.pop(identity.path, None)
            if old is not None:
                stale.append(self._pools.pop(old))
            while len(self._pools) >= self._max:
                evicted, evicted_pool = self._pools.popitem(last=False)
                del self._by_path[evicted.path]
                stale.append(evicted_pool)
            pool = self._pools[identity] = _ReaderPool(identity.path, self._per_cog)
            self._by_path[identity.path] = identity
        for gone in stale:
            gone.close()
        return pool

    def close(self) -> None:
        with self._lock:
            pools, self._pools = list(self._pools.values()), OrderedDict()
            self._by_path.clear()
        for pool in pools:
            pool.close()


# -- Rendered tiles -------------------------------------------------------------------------------

TileKey = tuple[CogIdentity, int, int, int]
TileOutcome = bytes | bool  # a PNG, or no tile: True off the tile grid, False outside the raster's bounds


class TileCache:
    """Rendered tiles (their :data:`TileOutcome`), LRU, at most ``max_bytes`` in all; ``max_bytes=0`` keeps
    nothing. Tiles outside a raster are kept too: a map viewer asks for them at every edge."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.bytes = 0
        self._entries: OrderedDict[TileKey, TileOutcome] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._entries)

    def get(self, key: TileKey) -> TileOutcome | None:
        """The cached outcome, or None when there is none."""
        with self._lock:
            outcome = self._entries.get(key)
            if outcome is not None:
                self._entries.move_to_end(key)
            return outcome

    def put(self, key: TileKey, tile: TileOutcome) -> None:
        cost = _cost(tile)
        if cost > self.max_bytes:
            return
        with self._lock:
            if key in self._entries:
                self.bytes -= _cost(self._entries.pop(key))
            self._entries[key] = tile
            self.bytes += cost
            while self.bytes > self.max_bytes:
                _, evicted = self._entries.popitem(last=False)
                self.bytes -= _cost(evicted)


def _cost(tile: TileOutcome) -> int:
    return _ENTRY_OVERHEAD + (len(tile) if isinstance(tile, bytes) else 0)


# -- Both, as the routes use them -----------------------------------------------------------------


class Tiler:
    """Tiles and TileJSON facts of COGs, through a :class:`ReaderCache` and a :class:`TileCache`."""

    def __init__(self, cache_bytes: int, max_cogs: int, readers_per_cog: int) -> None:
        self.readers = ReaderCache(max_cogs, readers_per_cog)
        self.tiles = TileCache(cache_bytes)
        self._rendering: dict[TileKey, threading.Event] = {}  # tiles being rendered now, by one thread each
        self._rendering_lock = threading.Lock()

    def tile(self, identity: CogIdentity, z: int, x: int, y: int) -> bytes:
        """PNG of tile z/x/y of that COG version; :class:`TileNotFoundError` outside it."""
        if not 0 <= z <= MAX_ZOOM or x < 0 or y < 0:
            raise TileNotFoundError(off_grid=True)
        key = (identity, z, x, y)
        outcome = self.tiles.get(key)
        if outcome is None:
            outcome = self._render_once(key)
        if isinstance(outcome, bool):
            raise TileNotFoundError(off_grid=outcome)
        return outcome

    def _render_once(self, key: TileKey) -> TileOutcome:
        """Render a tile not in the cache. Viewers that open the same place ask for the same tiles at once:
        one thread renders, the others wait for it and take its tile from the cache."""
        if self.tiles.max_bytes == 0:
            return self._render(key)
        with self._rendering_lock:
            done = self._rendering.get(key)
            leader = done is None
            if done is None:
                done = self._rendering[key] = threading.Event()
        if not leader:
            done.wait()
            outcome = self.tiles.get(key)
            if outcome is not None:
                return outcome  # else the leader failed or its tile did not fit: render it here
        try:
            outcome = self._render(key)
            self.tiles.put(key, outcome)
            return outcome
        finally:
            if leader:
                with self._rendering_lock:
                    del self._rendering[key]
                done.set()

    def _render(self, key: TileKey) -> TileOutcome:
        identity, z, x, y = key
        with self.readers.borrow(identity) as (cog, _):
            try:
                return cog.render(z, x, y)
            except TileNotFoundError as missing:
                return missing.off_grid

    def sample(self, identity: CogIdentity, x: float, y: float, lonlat: bool) -> float | None:
        """The first band's value at a point of that COG version: lon/lat degrees (``lonlat``, a raster with a
        CRS) or the raster's own pixel column and row (x, y); None outside it or on its nodata value."""
        with self.readers.borrow(identity) as (cog, _):
            return sample_dataset(cog.dataset, x, y, lonlat)

    def info(self, identity: CogIdentity) -> CogInfo:
        with self.readers.borrow(identity) as (cog, pool):
            if pool is None:
                return cog.info()
            if pool.info is None:
                pool.info = cog.info()
            return pool.info

    def close(self) -> None:
        self.readers.close()
