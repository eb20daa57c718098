"""Process settings, read once from the environment (prefix ``FOTOSKHEMA_``)."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import AliasChoices, Field
from pydantic_settings import BaseSettings, SettingsConfigDict

OSM_TILES = "https://tile.openstreetmap.org/{z}/{x}/{y}.png"  # OpenStreetMap's standard tiles


class Settings(BaseSettings):
    """Everything a process needs to know about its surroundings.

    ``DATABASE_URL`` and ``REDIS_URL`` are also accepted without the prefix, as docker compose and
    hosting platforms usually name them.
    """

    model_config = SettingsConfigDict(env_prefix="FOTOSKHEMA_", extra="ignore", populate_by_name=True)

    data_dir: Path = Path("data")  # flights, job workspaces and the SQLite file live here
    database_url: str = Field(
        default="",  # empty: SQLite at <data_dir>/fotoskhema.db
        validation_alias=AliasChoices("FOTOSKHEMA_DATABASE_URL", "DATABASE_URL"),
    )
    redis_url: str = Field(
        default="redis://127.0.0.1:6379/0",
        validation_alias=AliasChoices("FOTOSKHEMA_REDIS_URL", "REDIS_URL"),
    )
    max_upload_bytes: int = 400 * 1024 * 1024  # per file; larger files are answered 413
    max_image_pixels: int = 250_000_000  # width*height; a 135 MP aerial frame fits, a bomb does not
    max_image_side: int = 100_000  # px, either dimension
    min_image_side: int = 16  # px, either dimension
    # XYZ template of the viewer's basemap, shown when the browser is online; empty or "none": no basemap
    basemap_url: str = OSM_TILES
    web_dir: Path = Path(__file__).resolve().parent.parent / "web"  # the static viewer
    sse_poll_seconds: float = 0.5  # how often the event stream looks at the job record
    celery_queue: str = "cpu"  # queue the pipeline's tasks are sent to
    # the parts of GPU stages (features, matching) go to this queue when a worker there is alive (a GPU worker:
    # `fotoskhema worker --gpu N`); the other parts and stages to the job's queue
    gpu_queue: str = "gpu"
    parts_per_worker: int = Field(default=4, ge=1, le=1000)  # chunks of a stage's parts per live worker
    part_retries: int = Field(default=2, ge=0, le=20)  # a part that crashes is tried again, alone, this often

    # -- Access ----------------------------------------------------------------------------------
    public_read: bool = False  # anyone may read flights, jobs, outputs and tiles without a token
    allowed_hosts: list[str] = ["127.0.0.1", "localhost", "::1"]  # Host headers served; "*" serves any
    cors_origins: list[str] = []  # browser origins allowed to call the API from another site; none by default
    secret_key: str = ""  # signs tile and download URLs; empty: a random key kept in <data_dir>/secret_key
    signed_url_seconds: int = 12 * 3600  # how long a signed tile or download URL stays valid

    # -- Tiles -----------------------------------------------------------------------------------
    tile_cache_bytes: int = Field(default=256 * 1024 * 1024, ge=0)  # rendered tiles kept per process; 0: none
    tile_open_cogs: int = Field(default=32, ge=0)  # COGs kept open per process (LRU); 0: open one per request
    tile_readers_per_cog: int = Field(default=4, ge=1, le=64)  # handles of one open COG, one thread each
    tile_max_age_seconds: int = Field(default=3600, ge=0)  # browser reuse of a succeeded job's tile, s

    # -- Request limits --------------------------------------------------------------------------
    max_request_bytes: int = Field(default=2 * 1024**3, ge=1)  # one upload request, all its files; more: 413 unread
    max_files_per_request: int = Field(default=500, ge=1)  # parts (files and fields) of one multipart request
    max_mesh_bytes: int = Field(default=64 * 1024 * 1024, ge=1)  # a crack survey's mesh file (OBJ, PLY, STL)
    image_decode_budget_bytes: int = Field(default=1024**3, ge=1)  # pixels that full decodes (TIFF) hold at once

    # -- Large routes: resumable uploads (tus 1.0.0) and server-side import ---------------------------
    upload_expiry_seconds: int = Field(default=24 * 3600, ge=1)  # an unfinished upload idle this long is deleted, s
    resumable_upload_bytes: int = Field(default=32 * 1024**2, ge=0)  # the viewer sends files this large by tus; 0: all
    resumable_chunk_bytes: int = Field(default=32 * 1024**2, ge=64 * 1024)  # bytes per PATCH the viewer sends
    import_dirs: list[Path] = []  # folders of this machine whose sub-folders may be imported; empty: import off
    max_import_files: int = Field(default=20_000, ge=1)  # photos one import may name; a larger folder: 413

    # -- Liveness --------------------------------------------------------------------------------
    heartbeat_seconds: float = Field(default=10.0, gt=0)  # how often a running stage stamps its job's record
    stale_seconds: float = Field(default=60.0, gt=0)  # a stage silent this long is dead; a waiting job, lost
    reaper_seconds: float = Field(default=15.0, ge=0)  # how often the API looks for dead or lost jobs; 0: never
    max_deliveries: int = Field(default=3, ge=1, le=100)  # starts of one stage whose process died, then: failed
    stage_time_limit_seconds: int = Field(default=24 * 3600, ge=60)  # longest one stage may run, s (soft limit)
    worker_beacon_seconds: float = Field(default=10.0, gt=0)  # how often a worker says it is alive, in Redis

    def basemap(self) -> str:
        """The basemap template the viewer uses: "" when ops turned it off (empty or "none")."""
        url = self.basemap_url.strip()
        return "" if url.lower() in ("", "none") else url

    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'fotoskhema.db').resolve()}"


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings, built once."""
    return Settings()
