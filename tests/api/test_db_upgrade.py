"""A database made by an earlier version (``jobs.flight_id`` NOT NULL) is upgraded on start, keeping its jobs."""

from __future__ import annotations

from sqlalchemy import MetaData, create_engine, select

from core.db import Base, Database, Flight, Image, Job, utcnow


def test_old_database_accepts_calibration_jobs_and_keeps_its_records(api_settings) -> None:
    url = api_settings.resolved_database_url()
    api_settings.data_dir.mkdir(parents=True, exist_ok=True)
    old = MetaData()
    for table in Base.metadata.sorted_tables:
        table.to_metadata(old)
    old.tables["jobs"].c.flight_id.nullable = False  # the schema before calibration jobs
    engine = create_engine(url)
    old.create_all(engine)
    with engine.begin() as conn:
        flight_id = conn.execute(
            old.tables["flights"].insert().values(name="park", description="", created_at=utcnow())
        ).inserted_primary_key[0]
        old_id = conn.execute(
            old.tables["jobs"]
            .insert()
            .values(
                flight_id=flight_id,
                kind="mosaic",
                status="succeeded",
                stage="write_report",
                progress=100.0,
                progress_detail="done",
                timings={"load_images": 1.5},
                options={"mode": "planar"},
                error="",
                celery_id="c1",
                created_at=utcnow(),
                updated_at=utcnow(),
            )
        ).inserted_primary_key[0]
    engine.dispose()

    db = Database(url)
    with db.session() as s:
        new = Job(flight_id=None, kind="calibration", options={}, status="queued")
        s.add(new)
        s.flush()
        new_id = new.id
    with db.session() as s:
        jobs = {j.id: j for j in s.scalars(select(Job))}
        kept = jobs[old_id]
        assert kept.flight_id == flight_id and kept.timings == {"load_images": 1.5} and kept.status == "succeeded"
        assert jobs[new_id].flight_id is None and jobs[new_id].kind == "calibration"
    Database(url)  # a second start finds nothing to upgrade


def test_database_from_before_accounts_gets_the_new_columns_and_keeps_its_rows(api_settings) -> None:
    from sqlalchemy import Column, Table, inspect

    url = api_settings.resolved_database_url()
    api_settings.data_dir.mkdir(parents=True, exist_ok=True)
    new_columns = {"flights": {"owner_id"}, "jobs": {"owner_id", "heartbeat_at", "deliveries", "heartbeat_by"}}
    old = MetaData()
    for table in Base.metadata.sorted_tables:
        if table.name in ("users", "api_tokens"):
            continue
        keep = [c for c in table.columns if c.name not in new_columns.get(table.name, set())]
        Table(table.name, old, *(Column(c.name, c.type, primary_key=c.primary_key) for c in keep))
    engine = create_engine(url)
    old.create_all(engine)
    with engine.begin() as conn:
        conn.execute(old.tables["flights"].insert().values(id=7, name="park", description="", created_at=utcnow()))
        conn.execute(
            old.tables["jobs"]
            .insert()
            .values(
                id=3,
                flight_id=7,
                kind="mosaic",
                status="succeeded",
                stage="write_report",
                progress=100.0,
                progress_detail="done",
                timings={},
                options={},
                error="",
                celery_id="c1",
                created_at=utcnow(),
                updated_at=utcnow(),
            )  # fmt: skip
        )
    engine.dispose()

    db = Database(url)
    columns = {t: {c["name"] for c in inspect(db.engine).get_columns(t)} for t in new_columns}
    assert all(new_columns[t] <= columns[t] for t in new_columns)
    with db.session() as s:
        job = s.get(Job, 3)
        assert job is not None and job.owner_id is None and job.deliveries == 0 and job.status == "succeeded"
        assert job.flight_id == 7 and s.get(Flight, 7) is not None
        s.add(Image(flight_id=7, seq=1, filename="a.jpg", stored_name="a.jpg", size_bytes=1, width=1, height=1))
    with db.session() as s:  # the newest job and flight deleted: their ids are not given again
        s.delete(s.get(Job, 3))
    with db.session() as s:
        new = Job(flight_id=7, kind="mosaic", options={}, status="queued")
        s.add(new)
        s.flush()
        assert new.id != 3
        assert len(s.get(Flight, 7).images) == 1
    Database(url)  # a second start finds nothing to upgrade


def test_database_with_32_bit_image_sizes_takes_frames_over_2_gib(api_settings) -> None:
    from sqlalchemy import Integer

    url = api_settings.resolved_database_url()
    api_settings.data_dir.mkdir(parents=True, exist_ok=True)
    old = MetaData()
    for table in Base.metadata.sorted_tables:
        table.to_metadata(old)
    old.tables["images"].c.size_bytes.type = Integer()  # the schema before strip frames
    engine = create_engine(url)
    old.create_all(engine)
    with engine.begin() as conn:
        flight_id = conn.execute(
            old.tables["flights"].insert().values(name="route", description="", created_at=utcnow())
        ).inserted_primary_key[0]
        conn.execute(
            old.tables["images"]
            .insert()
            .values(flight_id=flight_id, seq=1, filename="a.tif", stored_name="a.tif", size_bytes=5, width=1, height=1)
        )
    engine.dispose()

    db = Database(url)
    big = 3 * 2**30 + 17  # a 135 MP strip frame in a BigTIFF can be this big
    with db.session() as s:
        s.add(
            Image(flight_id=flight_id, seq=2, filename="b.tif", stored_name="b.tif", size_bytes=big, width=1, height=1)
        )
    with db.session() as s:
        sizes = sorted(image.size_bytes for image in s.scalars(select(Image)))
    assert sizes == [5, big]
    Database(url)  # a second start finds nothing to upgrade
