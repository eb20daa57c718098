"""Job records: flights, their images and the jobs run on them (SQLAlchemy 2)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    String,
    Text,
    TypeDecorator,
    create_engine,
    event,
    inspect,
    text,
)
from sqlalchemy.engine import Dialect, Engine
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, relationship, sessionmaker

from core.kinds import JobStatus


def utcnow() -> datetime:
    return datetime.now(UTC)


class UtcDateTime(TypeDecorator[datetime]):
    """Timezone-aware UTC datetimes on every backend (SQLite stores them naive)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is not None and value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value


class Base(DeclarativeBase):
    type_annotation_map = {dict[str, Any]: JSON, datetime: UtcDateTime}


class User(Base):
    """Someone who may use the API; they authenticate with any of their unrevoked tokens."""

    __tablename__ = "users"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    is_admin: Mapped[bool] = mapped_column(Boolean, default=False)  # sees and may change everything
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    tokens: Mapped[list[ApiToken]] = relationship(back_populates="user", cascade="all, delete-orphan")


class ApiToken(Base):
    """An API token, stored as the SHA-256 of its secret: the secret itself is shown once, when made."""

    __tablename__ = "api_tokens"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id"), index=True)
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)  # hex SHA-256 of the whole token
    prefix: Mapped[str] = mapped_column(String(16))  # the token's first characters, to tell tokens apart
    label: Mapped[str] = mapped_column(String(200), default="")
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    last_used_at: Mapped[datetime | None] = mapped_column(nullable=True)
    revoked_at: Mapped[datetime | None] = mapped_column(nullable=True)
    user: Mapped[User] = relationship(back_populates="tokens")


class Flight(Base):
    __tablename__ = "flights"
    # ids are never given again (SQLite would reuse a deleted last one): a job's files, signed URLs and running
    # stages are keyed by them
    __table_args__ = {"sqlite_autoincrement": True}

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    # who made it; None for flights made before accounts, which only admins see
    owner_id: Mapped[int | None] = mapped_column(ForeignKey("users.id"), index=True, nullable=True)
    name: Mapped[str] = mapped_column(String(200))
    description: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    images: Mapped[list[Image]] = relationship(
        back_populates="flight", order_by="Image.seq", cascade="all, delete-orphan"
    )


class Image(Base):
    __tablename__ = "images"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    flight_id: Mapped[int] = mapped_column(ForeignKey("flights.id"), index=True)
    seq: Mapped[int] = mapped_column(Integer)  # upload order within the flight, from 1
    filename: Mapped[str] = mapped_column(String(255))  # as the client named it, for display only
    stored_name: Mapped[str] = mapped_column(String(64))  # chosen by the server, inside the flight folder
    size_bytes: Mapped[int] = mapped_column(BigInteger)  # a strip frame may be over 2 GiB
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    meta: Mapped[dict[str, Any]] = mapped_column(default=dict)  # GPS, focal length, attitude (EXIF/XMP)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    flight: Mapped[Flight] = relationship(back_populates="images")


class Job(Base):
    __tablename__ = "jobs"
    __table_args__ = {"sqlite_autoincrement": True}  # as for flights

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    # None for calibration jobs, whose photos are stored in the job's own folder
    flight_id: Mapped[int | None] = mapped_column(ForeignKey("flights.id"), index=True, nullable=True)
    # who made it; None for jobs made before accounts, which only admins see
    owner_id: Mapped[int | None] = mapped_column(ForeignKey("users.id"), index=True, nullable=True)
    kind: Mapped[str] = mapped_column(String(32))
    status: Mapped[str] = mapped_column(String(16), default=JobStatus.queued, index=True)
    stage: Mapped[str] = mapped_column(String(64), default="")
    progress: Mapped[float] = mapped_column(Float, default=0.0)  # 0-100, weighted over the stages
    progress_detail: Mapped[str] = mapped_column(String(200), default="")  # e.g. "frame 4/12"
    timings: Mapped[dict[str, Any]] = mapped_column(default=dict)  # stage -> wall seconds
    options: Mapped[dict[str, Any]] = mapped_column(default=dict)  # as requested, before defaults
    error: Mapped[str] = mapped_column(Text, default="")
    celery_id: Mapped[str] = mapped_column(String(64), default="")
    heartbeat_at: Mapped[datetime | None] = mapped_column(nullable=True)  # last sign of life of its running stage
    deliveries: Mapped[int] = mapped_column(Integer, default=0)  # starts of the current stage, reset when it ends
    heartbeat_by: Mapped[str] = mapped_column(String(200), default="")  # "host:pid" of the process running it
    # what its time left is estimated from (core.eta): {"frames": inputs, "stages": {stage: {seconds, unit, count}},
    # "current": {stage, started_at (epoch s), fraction, unit, done, total}}
    work: Mapped[dict[str, Any] | None] = mapped_column(default=dict, nullable=True)  # NULL in jobs made before it
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow, onupdate=utcnow)


class Upload(Base):
    """A resumable (tus) upload of one photo into a flight: its bytes so far are in a part file of the flight's
    folder (``workers.workspace.flight_upload_path``); once all arrived and checked, ``image_id`` names the photo."""

    __tablename__ = "uploads"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)  # random hex, the last part of its URL
    flight_id: Mapped[int] = mapped_column(ForeignKey("flights.id", ondelete="CASCADE"), index=True)
    owner_id: Mapped[int | None] = mapped_column(ForeignKey("users.id"), nullable=True)
    filename: Mapped[str] = mapped_column(String(255))  # as the client named it, for display only
    metadata_header: Mapped[str] = mapped_column(Text, default="")  # Upload-Metadata as sent, given back by HEAD
    length: Mapped[int] = mapped_column(BigInteger)  # Upload-Length, bytes
    offset: Mapped[int] = mapped_column(BigInteger, default=0)  # bytes stored for good (synced to disk)
    image_id: Mapped[int | None] = mapped_column(Integer, nullable=True)  # the photo it became, once complete
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[datetime] = mapped_column(index=True)  # moved on by every PATCH; then it is deleted


class FolderImport(Base):
    """A server-side import of a folder under one of ``Settings.import_dirs`` into a flight, and its progress."""

    __tablename__ = "imports"
    __table_args__ = {"sqlite_autoincrement": True}

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    flight_id: Mapped[int] = mapped_column(ForeignKey("flights.id", ondelete="CASCADE"), index=True)
    owner_id: Mapped[int | None] = mapped_column(ForeignKey("users.id"), nullable=True)
    root: Mapped[int] = mapped_column(Integer)  # index into Settings.import_dirs
    path: Mapped[str] = mapped_column(Text)  # the folder, relative to that root, as the client named it
    status: Mapped[str] = mapped_column(String(16), default="running")  # running, succeeded, failed, cancelled
    total: Mapped[int] = mapped_column(Integer, default=0)  # photo files found in the folder
    done: Mapped[int] = mapped_column(Integer, default=0)  # of them looked at so far
    imported: Mapped[int] = mapped_column(Integer, default=0)  # became photos of the flight
    skipped: Mapped[int] = mapped_column(Integer, default=0)  # already in the flight (same file or same bytes)
    refused: Mapped[int] = mapped_column(Integer, default=0)  # not photos this service takes (why: ``errors``)
    bytes_copied: Mapped[int] = mapped_column(BigInteger, default=0)  # disk used by copies (hard links use none)
    errors: Mapped[dict[str, Any]] = mapped_column(default=dict)  # file name -> why it was refused (the first 200)
    gps: Mapped[dict[str, Any]] = mapped_column(default=dict)  # the folder's GPS side file, as PUT /gps answers
    error: Mapped[str] = mapped_column(Text, default="")  # why the whole import stopped, if it did
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow, onupdate=utcnow)  # a running one's sign of life


class NodeOdmTask(Base):
    """A task made over the NodeODM-compatible routes (WebODM's processing-node API, ``api/routes/nodeodm.py``):
    the flight its photos go to and, once committed, the mosaic job that processes them. No foreign keys: the
    flight and job are deleted on their own (a task whose flight is gone is gone too)."""

    __tablename__ = "nodeodm_tasks"

    uuid: Mapped[str] = mapped_column(String(36), primary_key=True)
    owner_id: Mapped[int | None] = mapped_column(Integer, index=True, nullable=True)
    flight_id: Mapped[int] = mapped_column(Integer)
    job_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    name: Mapped[str] = mapped_column(String(200), default="")
    # {"given": NodeODM's [{name, value}] as sent, "job": the mosaic options they map to, "ignored": [names]}
    options: Mapped[dict[str, Any]] = mapped_column(default=dict)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Database:
    """An engine and its session factory; the schema is created on start."""

    def __init__(self, url: str) -> None:
        connect_args: dict[str, Any] = {}
        if url.startswith("sqlite"):
            # The API's threads and the worker processes share one file: wait for locks, don't fail.
            connect_args = {"check_same_thread": False, "timeout": 30}
        self.engine: Engine = create_engine(url, connect_args=connect_args, pool_pre_ping=True)
        if url.startswith("sqlite"):
            event.listen(self.engine, "connect", _sqlite_pragmas)
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)
        Base.metadata.create_all(self.engine)
        _add_missing_columns(self.engine)
        _allow_jobs_without_flight(self.engine)
        _never_reuse_ids(self.engine)
        _widen_byte_counts(self.engine)

    @contextmanager
    def session(self) -> Iterator[Session]:
        """A session that commits on success and rolls back on any error."""
        with self._sessions() as session, session.begin():
            yield session


def _add_missing_columns(engine: Engine) -> None:
    """Upgrade a database made by an earlier version: add the columns its tables lack (all nullable or
    with a default), keeping every row. ``create_all`` has already made any table it lacked."""
    inspector = inspect(engine)
    for table in Base.metadata.sorted_tables:
        present = {c["name"] for c in inspector.get_columns(table.name)}
        missing = [c for c in table.columns if c.name not in present]
        if not missing:
            continue
        with engine.begin() as conn:
            for column in missing:
                kind = column.type.compile(dialect=engine.dialect)
                default = getattr(column.default, "arg", None) if column.default is not None else None
                default = None if callable(default) else default
                fill = "" if default is None else f" NOT NULL DEFAULT {_sql_literal(default)}"
                conn.execute(text(f"ALTER TABLE {table.name} ADD COLUMN {column.name} {kind}{fill}"))


def _never_reuse_ids(engine: Engine) -> None:
    """Upgrade a SQLite database made before ids were AUTOINCREMENT: rebuild ``flights`` and ``jobs`` with it,
    keeping every row and id. Foreign keys are off meanwhile and references are not rewritten by the rename
    (``legacy_alter_table``), so ``images`` and ``jobs`` point at the rebuilt ``flights``."""
    if engine.dialect.name != "sqlite":
        return
    for table in (Base.metadata.tables["flights"], Base.metadata.tables["jobs"]):
        with engine.connect() as conn:
            ddl = conn.scalar(text("SELECT sql FROM sqlite_master WHERE type='table' AND name=:n"), {"n": table.name})
        if ddl is None or "AUTOINCREMENT" in ddl.upper():
            continue
        with engine.connect() as conn:
            conn.exec_driver_sql("PRAGMA foreign_keys=OFF")
            conn.exec_driver_sql("PRAGMA legacy_alter_table=ON")
            conn.commit()
            try:
                _rebuild(conn, table)
                conn.commit()
            finally:
                conn.rollback()
                conn.exec_driver_sql("PRAGMA legacy_alter_table=OFF")
                conn.exec_driver_sql("PRAGMA foreign_keys=ON")
                conn.commit()


def _rebuild(conn: Any, table: Any) -> None:
    """Make ``table`` again from the model, with its rows (in the caller's transaction)."""
    old = f"{table.name}_before_upgrade"
    conn.execute(text(f"ALTER TABLE {table.name} RENAME TO {old}"))
    for index in table.indexes:
        conn.execute(text(f"DROP INDEX IF EXISTS {index.name}"))
    table.create(conn)
    names = ", ".join(c.name for c in table.columns)
    conn.execute(text(f"INSERT INTO {table.name} ({names}) SELECT {names} FROM {old}"))
    conn.execute(text(f"DROP TABLE {old}"))


def _sql_literal(value: Any) -> str:
    if isinstance(value, bool):
        return "TRUE" if value else "FALSE"
    if isinstance(value, int | float):
        return repr(value)
    return "'" + str(value).replace("'", "''") + "'"


def _allow_jobs_without_flight(engine: Engine) -> None:
    """Upgrade a database made before calibration jobs, whose ``jobs.flight_id`` was NOT NULL.

    PostgreSQL drops the constraint in place; SQLite cannot, so the table is rebuilt and its rows copied,
    in one transaction: every job already recorded is kept as it was.
    """
    column = next(c for c in inspect(engine).get_columns("jobs") if c["name"] == "flight_id")
    if column["nullable"]:
        return
    with engine.begin() as conn:
        if engine.dialect.name != "sqlite":
            conn.execute(text("ALTER TABLE jobs ALTER COLUMN flight_id DROP NOT NULL"))
            return
        _rebuild(conn, Base.metadata.tables["jobs"])


def _widen_byte_counts(engine: Engine) -> None:
    """Upgrade a PostgreSQL database made when ``images.size_bytes`` was a 32-bit INTEGER (a 2 GiB frame
    overflowed it). SQLite's INTEGER is 64-bit already."""
    if engine.dialect.name == "sqlite":
        return
    column = next(c for c in inspect(engine).get_columns("images") if c["name"] == "size_bytes")
    if isinstance(column["type"], BigInteger):
        return
    with engine.begin() as conn:
        conn.execute(text("ALTER TABLE images ALTER COLUMN size_bytes TYPE BIGINT"))


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")  # readers (SSE, API) never block the writing worker
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.close()
