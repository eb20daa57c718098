"""A database made by an earlier version (``jobs.flight_id`` NOT NULL) is upgraded on start, keeping its jobs."""

from __future__ import annotations

from sqlalchemy import MetaData, create_engine, select

from core.db import Base, Database, Job, utcnow


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
