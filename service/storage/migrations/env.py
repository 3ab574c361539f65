"""Alembic environment.  The app passes its own connection (config.attributes["connection"]); the
`alembic` command line (alembic.ini at the repository root) uses LEARNEST_DATABASE_URL or the SQLite file
under LEARNEST_HOME, exactly like the app."""
from alembic import context

from learnest.service.config import Settings
from learnest.service.storage.tables import Base

config = context.config
target_metadata = Base.metadata


def _url() -> str:
    return config.get_main_option("sqlalchemy.url") or Settings().url


def run_offline() -> None:
    context.configure(url=_url(), target_metadata=target_metadata, literal_binds=True)
    with context.begin_transaction():
        context.run_migrations()


def _run(connection) -> None:
    context.configure(connection=connection, target_metadata=target_metadata,
                      render_as_batch=connection.dialect.name == "sqlite")  # SQLite cannot ALTER much
    with context.begin_transaction():
        context.run_migrations()


def run_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:
        _run(connection)
        return
    # the same engine setup (pragmas, BEGIN IMMEDIATE) as the app
    from learnest.service.storage.database import Database

    database = Database(_url())
    with database.engine.begin() as connection:
        _run(connection)
    database.dispose()


if context.is_offline_mode():
    run_offline()
else:
    run_online()
