"""The fleet registry's database: trucks, uploaded files, model versions, identification jobs and API tokens.

SQLAlchemy Core, so the same schema and queries run on SQLite (the zero-configuration default, one file in the
data directory) and PostgreSQL (`postgresql+psycopg://...`). Migrations are a numbered list applied in order
and recorded in `schema_version`: five tables do not need Alembic's extra dependency, migration folder and
env.py inside the wheel, and `fuelid token create --data-dir` migrates offline through the same function.

Times are Unix seconds (float, `*_unix_s`); message times of files are nanoseconds since the epoch (`*_ns`).
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.dialects import postgresql, sqlite

from fuelid.errors import InputError
from fuelid.fleet.storage import FILE_MODE, make_dir

metadata = sa.MetaData()

schema_version = sa.Table("schema_version", metadata, sa.Column("version", sa.Integer, nullable=False))

tokens = sa.Table(
    "tokens", metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("token_sha256", sa.String(64), nullable=False, unique=True),
    sa.Column("role", sa.String(16), nullable=False),  # admin | engineer | truck
    sa.Column("truck", sa.String(64)),  # the only truck a truck token uploads for
    sa.Column("name", sa.String(200), nullable=False, default=""),
    sa.Column("created_unix_s", sa.Float, nullable=False),
    sa.Column("revoked_unix_s", sa.Float),
)

trucks = sa.Table(
    "trucks", metadata,
    sa.Column("truck", sa.String(64), primary_key=True),
    sa.Column("created_unix_s", sa.Float, nullable=False),
)

files = sa.Table(
    "files", metadata,
    sa.Column("sha256", sa.String(64), primary_key=True),  # content address: one row per distinct file
    sa.Column("truck", sa.String(64), sa.ForeignKey("trucks.truck"), nullable=False, index=True),
    sa.Column("size_bytes", sa.BigInteger, nullable=False),
    sa.Column("start_ns", sa.BigInteger),
    sa.Column("end_ns", sa.BigInteger),
    sa.Column("messages", sa.BigInteger, nullable=False),
    sa.Column("uploaded_unix_s", sa.Float, nullable=False),
    sa.Column("name", sa.String(255)),  # the file's name on the uploader (v2); null for files uploaded before
)

jobs = sa.Table(
    "jobs", metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("truck", sa.String(64), sa.ForeignKey("trucks.truck"), nullable=False, index=True),
    sa.Column("reason", sa.String(32), nullable=False),  # request | fleet | new data
    sa.Column("status", sa.String(16), nullable=False),  # queued | running | done | failed
    sa.Column("created_unix_s", sa.Float, nullable=False),
    sa.Column("started_unix_s", sa.Float),
    sa.Column("finished_unix_s", sa.Float),
    sa.Column("error", sa.Text),
    sa.Column("model_version", sa.Integer),
)

models = sa.Table(
    "models", metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("truck", sa.String(64), sa.ForeignKey("trucks.truck"), nullable=False),
    sa.Column("version", sa.Integer, nullable=False),
    sa.Column("job_id", sa.Integer, sa.ForeignKey("jobs.id")),
    sa.Column("created_unix_s", sa.Float, nullable=False),
    sa.Column("model_sha256", sa.String(64), nullable=False),
    sa.Column("diagnosis_sha256", sa.String(64), nullable=False),
    sa.Column("report_sha256", sa.String(64)),
    sa.Column("metrics", sa.JSON, nullable=False),
    sa.Column("n_samples", sa.Integer),
    sa.Column("duration_s", sa.Float),
    sa.Column("top_effect", sa.String(64)),
    sa.UniqueConstraint("truck", "version", name="uq_models_truck_version"),
)

V1_TABLES = [tokens, trucks, files, jobs, models]


def _v1(conn) -> None:
    metadata.create_all(conn, tables=V1_TABLES)


def _v2(conn) -> None:
    """files.name: the uploaded file's own name, for reports and people (the blob store names files by their
    sha256). A database made by _v1 from today's tables has it already."""
    if "name" not in {c["name"] for c in sa.inspect(conn).get_columns("files")}:
        conn.execute(sa.text("ALTER TABLE files ADD COLUMN name VARCHAR(255)"))


# Append new migrations (functions of a connection) here; never edit one that has shipped.
MIGRATIONS = [_v1, _v2]


def database_url(data_dir: str | Path | None, url: str | None) -> str:
    """The database URL: `url` when given, else SQLite in `data_dir/fleet.db`."""
    if url:
        return url
    if data_dir is None:
        raise InputError("give a data directory or a database URL")
    return f"sqlite:///{Path(data_dir).resolve() / 'fleet.db'}"


def connect(url: str) -> sa.Engine:
    """An engine for `url`; SQLite gets WAL, a 30 s busy timeout and immediate write locks (BEGIN IMMEDIATE,
    so two writers queue instead of failing on a lock upgrade)."""
    if not url.startswith("sqlite"):
        return sa.create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=20)
    engine = sa.create_engine(url, connect_args={"timeout": 30, "check_same_thread": False},
                              pool_size=10, max_overflow=20)

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn, _record):
        dbapi_conn.isolation_level = None  # let SQLAlchemy's begin event below issue BEGIN
        cur = dbapi_conn.cursor()
        cur.execute("PRAGMA journal_mode=WAL")
        cur.execute("PRAGMA busy_timeout=30000")
        cur.execute("PRAGMA foreign_keys=ON")
        cur.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn):
        conn.exec_driver_sql("BEGIN IMMEDIATE")

    return engine


def migrate(engine: sa.Engine) -> int:
    """Apply the migrations not yet applied; return the schema version."""
    with engine.begin() as conn:
        metadata.create_all(conn, tables=[schema_version])
        current = conn.execute(sa.select(sa.func.max(schema_version.c.version))).scalar() or 0
        for version, step in enumerate(MIGRATIONS[current:], start=current + 1):
            step(conn)
            conn.execute(schema_version.insert().values(version=version))
        return len(MIGRATIONS)


def open_database(data_dir: str | Path | None = None, url: str | None = None,
                  file_mode: int | None = None) -> sa.Engine:
    """Connect and migrate. For SQLite in `data_dir`, a missing data_dir and fleet.db are created with
    storage.dir_mode(mode) and the mode (default storage.FILE_MODE; SQLite gives its -wal and -shm files the
    database file's mode); a `file_mode` given is also set on an existing fleet.db."""
    if not url and data_dir is not None:
        path = Path(data_dir) / "fleet.db"
        if not path.parent.exists():
            make_dir(path.parent, file_mode or FILE_MODE)
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT, file_mode or FILE_MODE))
        if file_mode is not None:
            os.chmod(path, file_mode)
    engine = connect(database_url(data_dir, url))
    migrate(engine)
    return engine


def insert_ignore(conn, table: sa.Table, **values) -> bool:
    """INSERT that does nothing when the primary/unique key exists; True when a row was inserted."""
    dialect = conn.dialect.name
    if dialect == "postgresql":
        insert = postgresql.insert
    elif dialect == "sqlite":
        insert = sqlite.insert
    else:
        raise InputError(f"unsupported database {dialect}")
    return conn.execute(insert(table).values(**values).on_conflict_do_nothing()).rowcount == 1


def add_file(engine: sa.Engine, *, sha256: str, truck: str, size_bytes: int, start_ns: int | None,
             end_ns: int | None, messages: int, name: str | None = None) -> bool:
    """Register a stored file (and its truck) with the name it had on the uploader; False when the hash was
    already registered."""
    now = time.time()
    with engine.begin() as conn:
        insert_ignore(conn, trucks, truck=truck, created_unix_s=now)
        return insert_ignore(conn, files, sha256=sha256, truck=truck, size_bytes=size_bytes, start_ns=start_ns,
                             end_ns=end_ns, messages=messages, uploaded_unix_s=now, name=name)


def get_file(engine: sa.Engine, sha256: str) -> dict | None:
    with engine.connect() as conn:
        row = conn.execute(sa.select(files).where(files.c.sha256 == sha256)).mappings().first()
    return dict(row) if row else None


def registered_hashes(engine: sa.Engine) -> set[str]:
    """Every sha256 a row names: uploaded files and model versions' model, diagnosis and report files."""
    m = models.c
    with engine.connect() as conn:
        hashes = set(conn.execute(sa.select(files.c.sha256)).scalars())
        for row in conn.execute(sa.select(m.model_sha256, m.diagnosis_sha256, m.report_sha256)):
            hashes.update(h for h in row if h)
    return hashes


def list_trucks(engine: sa.Engine) -> list[dict]:
    """Every truck with its file count, bytes, message time range and latest model version."""
    f = sa.select(files.c.truck, sa.func.count().label("files"), sa.func.sum(files.c.size_bytes).label("bytes"),
                  sa.func.min(files.c.start_ns).label("start_ns"), sa.func.max(files.c.end_ns).label("end_ns")
                  ).group_by(files.c.truck).subquery()
    m = sa.select(models.c.truck, sa.func.max(models.c.version).label("latest_model_version")
                  ).group_by(models.c.truck).subquery()
    q = (sa.select(trucks.c.truck, sa.func.coalesce(f.c.files, 0).label("files"),
                   sa.func.coalesce(f.c.bytes, 0).label("size_bytes"), f.c.start_ns, f.c.end_ns,
                   m.c.latest_model_version)
         .select_from(trucks.outerjoin(f, f.c.truck == trucks.c.truck).outerjoin(m, m.c.truck == trucks.c.truck))
         .order_by(trucks.c.truck))
    with engine.connect() as conn:
        return [dict(r) for r in conn.execute(q).mappings()]


def truck_exists(engine: sa.Engine, truck: str) -> bool:
    with engine.connect() as conn:
        return conn.execute(sa.select(trucks.c.truck).where(trucks.c.truck == truck)).first() is not None


def list_files(engine: sa.Engine, truck: str) -> list[dict]:
    q = sa.select(files).where(files.c.truck == truck).order_by(files.c.start_ns, files.c.sha256)
    with engine.connect() as conn:
        return [dict(r) for r in conn.execute(q).mappings()]


def list_models(engine: sa.Engine, truck: str) -> list[dict]:
    q = sa.select(models).where(models.c.truck == truck).order_by(models.c.version)
    with engine.connect() as conn:
        return [dict(r) for r in conn.execute(q).mappings()]


def get_model(engine: sa.Engine, truck: str, version: int | None) -> dict | None:
    """Model version `version` of `truck`, the latest when None."""
    q = sa.select(models).where(models.c.truck == truck)
    q = q.order_by(models.c.version.desc()) if version is None else q.where(models.c.version == version)
    with engine.connect() as conn:
        row = conn.execute(q.limit(1)).mappings().first()
    return dict(row) if row else None


def add_model(engine: sa.Engine, *, truck: str, job_id: int | None, **values) -> int:
    """Store a new model version of `truck` (the next number) and mark its job done; returns the version."""
    now = time.time()
    with engine.begin() as conn:
        latest = conn.execute(sa.select(sa.func.max(models.c.version)).where(models.c.truck == truck)).scalar()
        version = (latest or 0) + 1
        conn.execute(models.insert().values(truck=truck, version=version, job_id=job_id, created_unix_s=now,
                                            **values))
        if job_id is not None:
            conn.execute(jobs.update().where(jobs.c.id == job_id).values(
                status="done", finished_unix_s=now, model_version=version))
    return version


def create_job(engine: sa.Engine, truck: str, reason: str) -> dict:
    with engine.begin() as conn:
        job_id = conn.execute(jobs.insert().values(truck=truck, reason=reason, status="queued",
                                                   created_unix_s=time.time())).inserted_primary_key[0]
        return dict(conn.execute(sa.select(jobs).where(jobs.c.id == job_id)).mappings().one())


def update_job(engine: sa.Engine, job_id: int, **values) -> None:
    with engine.begin() as conn:
        conn.execute(jobs.update().where(jobs.c.id == job_id).values(**values))


def get_job(engine: sa.Engine, job_id: int) -> dict | None:
    with engine.connect() as conn:
        row = conn.execute(sa.select(jobs).where(jobs.c.id == job_id)).mappings().first()
    return dict(row) if row else None


def list_jobs(engine: sa.Engine, truck: str | None = None, active_only: bool = False, limit: int = 200) -> list[dict]:
    q = sa.select(jobs).order_by(jobs.c.id.desc()).limit(limit)
    if truck is not None:
        q = q.where(jobs.c.truck == truck)
    if active_only:
        q = q.where(jobs.c.status.in_(("queued", "running")))
    with engine.connect() as conn:
        return [dict(r) for r in conn.execute(q).mappings()]


def fail_interrupted_jobs(engine: sa.Engine) -> int:
    """Jobs left queued or running by a server that stopped: mark them failed (a refit can be asked again)."""
    with engine.begin() as conn:
        return conn.execute(jobs.update().where(jobs.c.status.in_(("queued", "running"))).values(
            status="failed", error="interrupted: the server stopped before the job finished",
            finished_unix_s=time.time())).rowcount
