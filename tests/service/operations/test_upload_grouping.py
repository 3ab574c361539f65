"""Grouping files into flights, one rule for every surface: an upload of several files (`group_uploads`) and the
CLI's local files (`service.local.flights.readable_groups`) both use `readable_groups`, on sample_logs/."""
from pathlib import Path

from learnest.service.local.flights import readable_groups as local_groups
from learnest.service.operations.uploads import LocalFile, group_uploads, readable_groups

SAMPLES = Path(__file__).resolve().parents[3] / "sample_logs"
FILES = ["circle_rep1.csv", "README.md", "pair_circle_vicon.csv", "mcap_figure8_json.mcap", "pair_circle_cfclient.csv"]


def test_flights_are_grouped_and_unreadable_files_left_out_with_their_reason():
    groups, left_out = readable_groups([SAMPLES / name for name in FILES])
    assert sorted((adapter, [p.name for p in files]) for adapter, files in groups) == [
        ("mcap", ["mcap_figure8_json.mcap"]), ("nanobench", ["circle_rep1.csv"]),
        ("vicon+cfclient", ["pair_circle_vicon.csv", "pair_circle_cfclient.csv"])]
    assert [(path.name, err.path) for path, err in left_out] == [("README.md", str(SAMPLES / "README.md"))]


def test_a_vicon_export_without_its_cfclient_log_is_left_out_and_the_others_kept():
    groups, left_out = readable_groups([SAMPLES / "pair_circle_vicon.csv", SAMPLES / "circle_rep2.csv"])
    assert [(adapter, [p.name for p in files]) for adapter, files in groups] == [("nanobench", ["circle_rep2.csv"])]
    [(path, err)] = left_out
    assert path.name == "pair_circle_vicon.csv" and "cfclient log" in err.problem


def test_the_cli_and_an_upload_group_the_same_files_the_same_way(tmp_path):
    paths = [SAMPLES / name for name in FILES]
    groups, errors = local_groups(paths)
    assert errors == [{"file": str(SAMPLES / "README.md"), "message": readable_groups(paths)[1][0][1].problem}]
    with open(paths[0], "rb") as a, open(paths[1], "rb") as b, open(paths[2], "rb") as c, \
            open(paths[3], "rb") as d, open(paths[4], "rb") as e:
        uploaded, refused = group_uploads([LocalFile(p.name, f) for p, f in zip(paths, (a, b, c, d, e))], tmp_path)
    by_upload = sorted(sorted(FILES[i] for i in members) for members in uploaded)
    by_cli = sorted(sorted(p.name for p in files) for _, files in groups)
    assert by_upload == by_cli
    assert list(refused) == [1] and refused[1].startswith("README.md: ")
