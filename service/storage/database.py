"""The Database handle: engine, short transactions, Alembic migrations, and a few typed query helpers.

SQLite (a file under LEARNEST_HOME) is the default; PostgreSQL when LEARNEST_DATABASE_URL is given.
Tables (`storage.tables`) are created only by the Alembic migrations in `storage/migrations` (the app runs
`upgrade head`).
"""
from __future__ import annotations

import fcntl
import json
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar, cast

from alembic.config import Config
from sqlalchemy import CursorResult, create_engine, event, exists, or_, select, text
from sqlalchemy.engine import Connection
from sqlalchemy.engine import Result as QueryResult
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session, sessionmaker

from learnest.errors import Conflict, NotFound
from learnest.ingest.flight import json_compatible

from .blobs import StorageUnavailable
from .tables import Base, FlightFile, FlightRecord, ModelVersion, Result

if TYPE_CHECKING:
    from .blobs import BlobStore

MIGRATIONS = Path(__file__).resolve().parent / "migrations"
SQLITE_FULL = 13            # sqlite3's result code "database or disk is full"
POSTGRES_DISK_FULL = "53100"


class DatabaseFull(StorageUnavailable):
    """The database cannot take a write: its disk (or its size limit) is full.  HTTP 507, as a full blob folder;
    the message says so without the SQL."""


def storage_is_full(err: BaseException) -> bool:
    """Whether a database error means "no space": SQLite's SQLITE_FULL, PostgreSQL's disk_full (53100)."""
    orig = getattr(err, "orig", err)
    if getattr(orig, "sqlite_errorcode", None) == SQLITE_FULL or "database or disk is full" in str(orig):
        return True
    return POSTGRES_DISK_FULL in (getattr(orig, "sqlstate", None), getattr(orig, "pgcode", None))


def database_full(err: BaseException) -> DatabaseFull:
    """The `DatabaseFull` to raise for ``err`` (see `storage_is_full`)."""
    return DatabaseFull("the server's database is full (no space left for it): nothing was stored; try again "
                        "once its operator has freed space")


def _json_dumps(value) -> str:
    return json.dumps(json_compatible(value))


# -- which blobs the rows name ------------------------------------------------------------------------
BLOB_COLUMNS = (FlightRecord.flight_blob, FlightFile.sha256, ModelVersion.weights_blob, Result.estimates_blob)


def referenced_blobs(db: Database) -> set[str]:
    """Every blob sha a row names: normalized flights, their raw files, model weights, stored estimates."""
    with db.transaction() as session:
        return {sha for column in BLOB_COLUMNS
                for sha in session.scalars(select(column).where(column.is_not(None))) if sha is not None}


def blob_is_referenced(db: Database, sha: str) -> bool:
    """Whether a flight, a raw file, a model version or a result's estimates name blob ``sha``."""
    with db.transaction() as session:
        return bool(session.scalar(select(or_(*(exists().where(column == sha) for column in BLOB_COLUMNS)))))


def discard_blobs(db: Database, blobs: BlobStore, shas: Iterable[str]) -> list[str]:
    """Remove blobs a failed write left behind (no row names them); best effort, never raises OSError (a blob
    that stays is an orphan the server's start-up sweep removes).  Call it outside `BlobStore.writing`."""
    return blobs.collect([sha for sha in shas if sha], lambda sha: blob_is_referenced(db, sha))


# -- the database handle ------------------------------------------------------------------------------
class Database:
    """Engine + session factory.  Use `with db.transaction() as session:` for short units of work: on
    SQLite every transaction takes the write lock up front (BEGIN IMMEDIATE), so holding one while doing
    slow work would block every other writer."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.is_sqlite = url.startswith("sqlite")
        if self.is_sqlite:
            self._prepare_sqlite_file()
            self.engine = create_engine(url, connect_args={"timeout": 60, "check_same_thread": False},
                                        json_serializer=_json_dumps)
            _sqlite_pragmas(self.engine)
        else:
            self.engine = create_engine(url, pool_pre_ping=True, json_serializer=_json_dumps)
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)

    def _prepare_sqlite_file(self) -> None:
        path = self.sqlite_path
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)

    @property
    def sqlite_path(self) -> Path | None:
        """The SQLite file of a ``sqlite:///`` URL; None for in-memory SQLite and other databases."""
        prefix = "sqlite:///"
        if not self.url.startswith(prefix) or self.url == prefix or ":memory:" in self.url:
            return None
        return Path(self.url[len(prefix):].split("?", 1)[0])

    def session(self) -> Session:
        """A new session (the caller commits and closes it); prefer `transaction`."""
        return self._sessions()

    @contextmanager
    def transaction(self) -> Iterator[Session]:
        """A session in a transaction: committed on exit, rolled back on an exception.  A database with no
        space left raises `DatabaseFull` (HTTP 507) instead of the driver's error."""
        try:
            with self._sessions.begin() as session:
                yield session
        except OperationalError as err:
            if storage_is_full(err):
                raise database_full(err) from err
            raise

    @contextmanager
    def reading(self) -> Iterator[Session]:
        """A session for reads only: on SQLite a deferred transaction, which takes no write lock (WAL: it
        never waits for a writer), for the look-ups every request makes (its token).  Rolled back on exit."""
        connection = self.engine.connect().execution_options(learnest_reading=True)
        try:
            with Session(bind=connection) as session:
                yield session
        finally:
            connection.close()

    def migrate(self) -> None:
        """Alembic `upgrade head`, serialized across processes (several uvicorn workers start at once)."""
        from alembic import command

        config = Config()
        config.set_main_option("script_location", str(MIGRATIONS))
        with self._migration_lock(), self.engine.connect() as connection:
            if self.is_sqlite:
                # A migration may rebuild a table (SQLite cannot ALTER it): with foreign keys enforced,
                # dropping the old copy would cascade-delete the rows that point at it.  The pragma only
                # takes effect outside a transaction, so it is set on the driver's connection first.
                _driver_connection(connection).execute("PRAGMA foreign_keys=OFF")
            try:
                with connection.begin():
                    if not self.is_sqlite:  # PostgreSQL: held until this transaction ends
                        connection.execute(text("SELECT pg_advisory_xact_lock(7261034)"))
                    config.attributes["connection"] = connection
                    command.upgrade(config, "head")
                    if self.is_sqlite and connection.exec_driver_sql("PRAGMA foreign_key_check").first():
                        raise RuntimeError("migration left rows whose foreign keys point nowhere")
            finally:
                if self.is_sqlite:
                    _driver_connection(connection).execute("PRAGMA foreign_keys=ON")

    def require_current_schema(self) -> None:
        """Raise `Conflict` unless the schema is at the newest migration; reads never migrate.

        Migrating is a write that belongs to whoever runs the service (`learnest serve` does it at start);
        a read (loading a model for `learnest evaluate`) against an older schema says so instead.
        """
        from alembic.migration import MigrationContext
        from alembic.script import ScriptDirectory

        config = Config()
        config.set_main_option("script_location", str(MIGRATIONS))
        head = ScriptDirectory.from_config(config).get_current_head()
        with self.engine.connect() as connection:
            current = MigrationContext.configure(connection).get_current_revision()
        if current != head:
            raise Conflict(f"the database is at schema revision {current or 'none'} and this learnest needs {head}: "
                           "start `learnest serve` once (it migrates) or run `alembic upgrade head`")

    @contextmanager
    def _migration_lock(self):
        path = self.sqlite_path
        if path is None:
            yield
            return
        with open(path.with_name(path.name + ".migrate.lock"), "a") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(handle, fcntl.LOCK_UN)

    def dispose(self) -> None:
        """Close the engine's pooled connections."""
        self.engine.dispose()


def _driver_connection(connection: Connection) -> Any:
    """The DBAPI driver's own connection under ``connection`` (sqlite3's, for the pragmas)."""
    driver = connection.connection.driver_connection
    if driver is None:  # only None once the pooled connection was invalidated
        raise RuntimeError("the database connection was closed during the migration")
    return driver


def _sqlite_pragmas(engine) -> None:
    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection, _record):
        dbapi_connection.isolation_level = None  # let SQLAlchemy's BEGIN below be the only one
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")      # readers never block the writer
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute("PRAGMA synchronous=FULL")      # a committed row survives a power cut
        cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(connection):
        # IMMEDIATE: take the write lock now (waiting up to the busy timeout) instead of failing with
        # "database is locked" when a read transaction later tries to write; `Database.reading` only reads
        reading = connection.get_execution_options().get("learnest_reading", False)
        connection.exec_driver_sql("BEGIN" if reading else "BEGIN IMMEDIATE")


# -- typed helpers ----------------------------------------------------------------------------------------
RowT = TypeVar("RowT", bound=Base)


def get_row(session: Session, table: type[RowT], key: Any, what: str, *, for_update: bool = False) -> RowT:
    """The row of ``table`` with primary key ``key``; `NotFound` (naming it ``what``) if there is none."""
    row = session.get(table, key, with_for_update=for_update)
    if row is None:
        raise NotFound(f"{what} {key} not found")
    return row


def flights_by_id(session: Session, ids: Iterable[int]) -> dict[int, FlightRecord]:
    """{id: flight row} of the flights among ``ids`` that exist."""
    return {f.id: f for f in session.scalars(select(FlightRecord).where(FlightRecord.id.in_(list(ids))))}


MISSING_LISTED = 10   # ids a "not found" message lists before it only counts the rest


def flights_not_found(missing: Sequence[int]) -> NotFound:
    """The 404 for flight ids that do not exist: the first MISSING_LISTED of them and how many more (a request
    naming 100 000 wrong ids got them all back, 600 kB)."""
    listed = ", ".join(map(str, missing[:MISSING_LISTED]))
    more = f" and {len(missing) - MISSING_LISTED} more" if len(missing) > MISSING_LISTED else ""
    return NotFound(f"flight(s) not found: {listed}{more} ({len(missing)} in all)" if more
                    else f"flight(s) not found: {listed}")


def dml_rowcount(result: QueryResult[Any]) -> int:
    """The number of rows an UPDATE / DELETE matched.  ``Session.execute`` is typed as returning a plain
    ``Result``, but for a DML statement SQLAlchemy returns a `CursorResult`, which has ``rowcount``."""
    return cast("CursorResult[Any]", result).rowcount


