"""Uploads racing for one flight name: every upload answered as stored holds its raw file, under any
interleaving.  Many drones' logs are all called ``log.csv``; the first upload takes the plain name, the
others retry under ``log-<sha8>`` - and a retry must store the raw file again, since the first attempt's
blobs were collected when its name was taken."""
from __future__ import annotations

import copy
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from utils.service import flight_csv, running_app, upload

RACE = 16      # uploads at once, as 16 drones' log.csv
ROUNDS = 20    # races run


@pytest.fixture(scope="module")
def template(tmp_path_factory):
    """One decoded flight: the stand-in decoder hands out copies of it, so a race costs no CSV parsing."""
    from learnest.service.jobs.reading import StagedFile, read_uploaded_flight
    from learnest.service.storage.blobs import sha256_bytes

    path = flight_csv(tmp_path_factory.mktemp("template"), 0)
    return read_uploaded_flight([StagedFile("log.csv", path, sha256_bytes(path.read_bytes()), 0, "log")])


def _stores(tmp_path):
    """A fresh database and blob store under ``tmp_path``."""
    from learnest.service.storage.blobs import BlobStore
    from learnest.service.storage.database import Database

    db, blobs = Database(f"sqlite:///{tmp_path / 'learnest.db'}"), BlobStore(tmp_path / "blobs")
    db.migrate()
    return db, blobs


def _store(db, blobs, template, contents: list[bytes], names: list[str], jitter: list[float]):
    """``contents`` uploaded at once (upload i named ``names[i]``, after ``jitter[i]`` s) through `add_flight`;
    -> [(row, created)] per upload."""
    from learnest.service.operations.uploads import LocalFile, add_flight

    start = threading.Barrier(len(contents))

    def decode(staged, **_choice):
        flight = copy.deepcopy(template)
        flight.meta["name"] = staged[0].original_name.rsplit(".", 1)[0]
        return flight

    def one(i: int):
        import io

        start.wait()
        time.sleep(jitter[i])
        return add_flight(db, blobs, [LocalFile(names[i], io.BytesIO(contents[i]))], decode=decode)

    with ThreadPoolExecutor(len(contents)) as pool:
        return list(pool.map(one, range(len(contents))))


def _assert_every_answer_holds_its_files(blobs, contents, answers) -> None:
    for content, (row, _created) in zip(contents, answers):
        [raw] = row.files
        assert blobs.exists(raw.sha256), f"{row.name}: raw file {raw.sha256[:12]} not stored"
        assert blobs.read_bytes(raw.sha256) == content
        assert blobs.exists(row.flight_blob)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_concurrent_same_name_uploads_never_answer_for_a_file_they_do_not_hold(tmp_path_factory, template, data):
    """Property: whatever the contents (repeats included), names and timing, every upload's answer - stored,
    or found stored already - names a flight whose raw file is in the blob store with that upload's bytes."""
    n = data.draw(st.integers(2, 10), label="uploads")
    distinct = data.draw(st.lists(st.binary(min_size=1, max_size=64), min_size=1, max_size=n, unique=True),
                         label="contents")
    contents = [data.draw(st.sampled_from(distinct)) for _ in range(n)]
    names = [data.draw(st.sampled_from(["log.csv", "log.CSV", "other.csv"])) for _ in range(n)]
    jitter = [data.draw(st.sampled_from([0.0, 0.0, 0.001, 0.005])) for _ in range(n)]
    db, blobs = _stores(tmp_path_factory.mktemp("race"))
    try:
        answers = _store(db, blobs, template, contents, names, jitter)
        _assert_every_answer_holds_its_files(blobs, contents, answers)
        assert len({row.id for row, _ in answers}) == len(set(contents))   # one flight per content
        assert sum(created for _, created in answers) == len(set(contents))
    finally:
        db.dispose()


def test_the_16_way_same_name_race_run_20_times_loses_no_file(tmp_path, template):
    """16 different logs all named log.csv at once, 20 times: every flight stored holds its raw file."""
    lost = []
    db, blobs = _stores(tmp_path)
    try:
        for round_ in range(ROUNDS):   # one name per round: log<round>, then log<round>-<sha8>
            contents = [f"drone {i} of round {round_}\n".encode() * (1 + i) for i in range(RACE)]
            answers = _store(db, blobs, template, contents, [f"log{round_}.csv"] * RACE, [0.0] * RACE)
            assert all(created for _, created in answers)
            assert len({row.name for row, _ in answers}) == RACE
            lost += [row.name for content, (row, _) in zip(contents, answers)
                     if not blobs.exists(row.files[0].sha256) or blobs.read_bytes(row.files[0].sha256) != content]
    finally:
        db.dispose()
    assert lost == []


def test_same_name_uploads_through_the_api_each_get_their_own_raw_file(tmp_path):
    """POST /flights of 8 different logs all named log.csv at once: each 201 flight's /raw is its own bytes."""
    logs = tmp_path / "logs"
    logs.mkdir()
    contents = [flight_csv(logs, seed).read_bytes() for seed in range(8)]
    for i, content in enumerate(contents):
        (logs / f"{i}.csv").write_bytes(content)
    with running_app(tmp_path / "home") as client, ThreadPoolExecutor(len(contents)) as pool:
        answers = list(pool.map(lambda i: upload(client, logs / f"{i}.csv", names=["log.csv"]), range(len(contents))))
        assert [a.status_code for a in answers] == [201] * len(contents), [a.text for a in answers]
        assert len({a.json()["name"] for a in answers}) == len(contents)
        for content, answer in zip(contents, answers):
            raw = client.get(f"/flights/{answer.json()['id']}/raw")
            assert raw.status_code == 200 and raw.content == content


def test_a_twin_that_takes_the_last_free_name_first_is_the_answer(tmp_path, template):
    """The interleaving a race can produce, made deterministic: another content holds ``log``; between this
    upload's look for its content (absent) and its choice of name, an upload of the very same bytes stores them
    as ``log-<sha8>``.  Both names are then taken, and the answer is the twin's flight, not a name conflict."""
    import io

    from learnest.service.operations.uploads import LocalFile, add_flight

    db, blobs = _stores(tmp_path)

    def decode(staged, **_choice):
        flight = copy.deepcopy(template)
        flight.meta["name"] = staged[0].original_name.rsplit(".", 1)[0]
        return flight

    twin: list = []

    def decode_after_the_twin(staged, **choice):
        twin.append(add_flight(db, blobs, [LocalFile("log.csv", io.BytesIO(b"drone x\n"))], decode=decode))
        return decode(staged, **choice)

    try:
        other, _ = add_flight(db, blobs, [LocalFile("log.csv", io.BytesIO(b"drone y\n"))], decode=decode)
        row, created = add_flight(db, blobs, [LocalFile("log.csv", io.BytesIO(b"drone x\n"))],
                                  decode=decode_after_the_twin)
        [(twin_row, twin_created)] = twin
        assert other.name == "log" and twin_created and twin_row.name.startswith("log-")
        assert (row.id, created) == (twin_row.id, False)
        _assert_every_answer_holds_its_files(blobs, [b"drone x\n"], [(row, created)])
    finally:
        db.dispose()
