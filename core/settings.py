"""Process settings, read once from the environment (prefix ``FOTOSKHEMA_``)."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import AliasChoices, Field
from pydantic_settings import BaseSettings, SettingsConfigDict


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
    basemap_url: str = ""  # optional XYZ template for the viewer's basemap; empty: no basemap
    web_dir: Path = Path(__file__).resolve().parent.parent / "web"  # the static viewer
    sse_poll_seconds: float = 0.5  # how often the event stream looks at the job record
    celery_queue: str = "cpu"  # queue the pipeline's tasks are sent to

    # -- Access ----------------------------------------------------------------------------------
    public_read: bool = False  # anyone may read flights, jobs, outputs and tiles without a token
    allowed_hosts: list[str] = ["127.0.0.1", "localhost", "::1"]  # Host headers served; "*" serves any
    cors_origins: list[str] = []  # browser origins allowed to call the API from another site; none by default
    secret_key: str = ""  # signs tile and download URLs; empty: a random key kept in <data_dir>/secret_key
    signed_url_seconds: int = 12 * 3600  # how long a signed tile or download URL stays valid

    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'fotoskhema.db').resolve()}"


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings, built once."""
    return Settings()
