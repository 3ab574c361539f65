"""Storage: ids are never handed out twice, on a new database and on one migrated from before the fix."""
from alembic import command
from alembic.config import Config
from utils.service import flight_csv, running_app, upload


def test_a_deleted_flights_id_is_never_given_to_the_next_upload(tmp_path, data_dir):
    with running_app(tmp_path / "home") as client:
        first = upload(client, flight_csv(data_dir, 40)).json()
        deleted = upload(client, flight_csv(data_dir, 41)).json()
        assert client.delete(f"/flights/{deleted['id']}").status_code == 204
        new = upload(client, flight_csv(data_dir, 42)).json()
        assert new["id"] > deleted["id"] > first["id"]
        # a retried DELETE of the old id deletes nothing else
        assert client.delete(f"/flights/{deleted['id']}").status_code == 404
        assert client.get(f"/flights/{new['id']}").status_code == 200


def _upgrade(database, revision: str) -> None:
    from learnest.service.storage.database import MIGRATIONS

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    with database.engine.begin() as connection:
        config.attributes["connection"] = connection
        command.upgrade(config, revision)


def _insert_flight(connection, name: str, flight_id: int | None = None) -> int:
    from sqlalchemy import text

    columns = "sha256, name, adapter, duration_s, rate_hz, samples, quality_ok, quality, flight_blob, meta, created_at"
    values = f"'{name:0>64}', '{name}', 'nanobench', 1.0, 100.0, 100, 1, '{{}}', 'b', '{{}}', '2026-01-01'"
    if flight_id is not None:
        columns, values = "id, " + columns, f"{flight_id}, " + values
    connection.execute(text(f"INSERT INTO flights ({columns}) VALUES ({values})"))
    return connection.execute(text(f"SELECT id FROM flights WHERE name = '{name}'")).scalar()


def test_migrating_an_old_database_keeps_its_rows_and_stops_id_reuse(tmp_path):
    from sqlalchemy import text

    from learnest.service.storage.database import Database

    database = Database(f"sqlite:///{tmp_path / 'old.db'}")
    _upgrade(database, "0002")                      # the schema before ids were protected
    with database.engine.begin() as connection:
        for flight_id in (1, 2, 3):
            _insert_flight(connection, f"f{flight_id}", flight_id)
            connection.execute(text(
                "INSERT INTO flight_files (flight_id, position, original_name, sha256, size_bytes, role) "
                f"VALUES ({flight_id}, 0, 'f{flight_id}.csv', 'x', 10, 'log')"))
        connection.execute(text("DELETE FROM flight_files WHERE flight_id = 3"))
        connection.execute(text("DELETE FROM flights WHERE id = 3"))
    database.migrate()                               # what the app does at start
    with database.engine.begin() as connection:
        assert connection.execute(text("SELECT count(*) FROM flight_files")).scalar() == 2  # nothing cascaded
        assert "AUTOINCREMENT" in connection.execute(
            text("SELECT sql FROM sqlite_master WHERE name = 'flights'")).scalar()
        # the rebuild can only know the ids it kept: the next is 3, and from then on none is reused
        assert _insert_flight(connection, "f4") == 3
        connection.execute(text("DELETE FROM flights WHERE id = 3"))
        assert _insert_flight(connection, "f5") == 4
    database.dispose()


def test_loading_a_model_never_migrates_an_older_database(tmp_path):
    """A read (learnest evaluate --model) against an older schema says how to upgrade, and changes nothing."""
    import pytest

    from learnest.errors import Conflict
    from learnest.service.config import Settings
    from learnest.service.storage.database import Database
    from learnest.service.storage.registry import load_model_ref

    home = tmp_path / "home"
    home.mkdir()
    database = Database(Settings(home=home).url)
    _upgrade(database, "0002")
    with pytest.raises(Conflict, match=r"schema revision 0002 and this learnest needs 00\d\d.*learnest serve"):
        load_model_ref("demo:1", Settings(home=home))
    with database.engine.connect() as connection:
        assert connection.exec_driver_sql("SELECT version_num FROM alembic_version").scalar() == "0002"
    database.dispose()


def test_migrating_to_0006_keeps_each_models_highest_version_so_a_deleted_number_is_never_reused(tmp_path):
    from sqlalchemy import text

    from learnest.service.storage.database import Database

    database = Database(f"sqlite:///{tmp_path / 'old.db'}")
    _upgrade(database, "0005")
    with database.engine.begin() as connection:
        flight_id = _insert_flight(connection, "f1")
        for name in ("quad", "empty"):
            connection.execute(text("INSERT INTO registered_models (name, created_at) "
                                    f"VALUES ('{name}', '2026-01-01')"))
        for version in (1, 3):
            connection.execute(text(
                "INSERT INTO model_versions (name, version, status, training_flight_id, hyperparameters, created_at) "
                f"VALUES ('quad', {version}, 'ready', {flight_id}, '{{}}', '2026-01-01')"))
    database.migrate()
    with database.engine.begin() as connection:
        rows = dict(connection.execute(text("SELECT name, last_version FROM registered_models")).all())
        assert rows == {"quad": 3, "empty": 0}
        assert connection.execute(text("SELECT count(*) FROM jobs WHERE stage IS NOT NULL")).scalar() == 0
    database.dispose()
