"""Error messages say what is wrong, in a bounded form."""
from __future__ import annotations

import re
import warnings

import pytest
from utils.service import flight_csv, running_app

from learnest.ingest import IngestError, read_flights
from learnest.ingest.formats.crazyflie_usd import decoder as usd_decoder
from learnest.ingest.formats.crazyflie_usd import writer as usd_writer
from learnest.ingest.formats.crazyflie_variables import ACC


def _without_column(source, target, column: str):
    rows = [line.split(",") for line in source.read_text().splitlines()]
    k = rows[0].index(column)
    target.write_text("\n".join(",".join(v for j, v in enumerate(row) if j != k) for row in rows) + "\n")
    return target


def test_a_nanobench_csv_without_a_column_names_the_column(data_dir):
    broken = _without_column(flight_csv(data_dir, 0), data_dir / "broken.csv", "pz")
    with pytest.raises(IngestError) as err:
        read_flights([broken])
    assert "column(s) pz" in str(err.value) and "unrecognised" not in str(err.value)


def test_a_usd_log_with_only_its_header_says_it_has_no_samples(tmp_path):
    from learnest.ingest.formats.crazyflie_usd.reader import POSE

    events = {"fixedFrequency": {"t": [0], "vars": {name: ("f", [0.0]) for name in ACC + POSE}}}
    data = usd_writer.encode(events)
    _version, event_types, header_end = usd_decoder.parse_header(data, "test")
    (tmp_path / "log").write_bytes(data[:header_end])   # the header, no record
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # the decoder warns about the missing trailer
        with pytest.raises(IngestError) as err:
            read_flights([tmp_path / "log"])
    assert "no samples" in str(err.value) and "inf" not in str(err.value)


def test_an_absurd_time_stamp_is_printed_in_a_bounded_form(data_dir):
    rows = [line.split(",") for line in flight_csv(data_dir, 0).read_text().splitlines()]
    rows[5][0] = "1e300"
    path = data_dir / "absurd.csv"
    path.write_text("\n".join(",".join(row) for row in rows) + "\n")
    with pytest.raises(IngestError) as err:
        read_flights([path])
    message = str(err.value)
    assert "1e+300 s" in message and len(message) < 300
    assert not re.search(r"\d{20}", message)   # never the 301 digits of the number written out


def test_a_very_long_file_name_is_a_4xx_naming_the_length_limit(tmp_path, data_dir):
    path = flight_csv(data_dir, 0)
    with running_app(tmp_path / "home") as client:
        answer = client.post("/flights", files=[("files", ("a" * 5000 + ".csv", path.read_bytes()))])
    assert answer.status_code == 400
    assert "file name too long" in answer.json()["detail"] and "4224 bytes" in answer.json()["detail"]
