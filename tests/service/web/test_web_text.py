"""The text of the report pages as a reader sees it: the answer first, the same sentence on the page and in
the CLI, spaces between values and units and between labels (no "rep1KNODE-UKF", "m/s²explains", "0.42 1")."""
from __future__ import annotations

import re
from html.parser import HTMLParser
from types import SimpleNamespace

import pytest

from learnest.service.cli import format_report
from learnest.service.web import evaluation_plots
from learnest.service.web.rendering import page
from learnest.workflows.headline import diagnosis_headline, diagnosis_split, evaluation_headline, gap_methods

BLOCKS = {"p", "div", "tr", "li", "ul", "table", "h1", "h2", "section", "details", "summary", "br", "td", "th",
          "form", "fieldset", "legend", "nav", "option", "select", "label"}


class _Text(HTMLParser):
    """Visible text as a browser lays it out: inline tags add nothing, block tags and cells break."""

    def __init__(self):
        super().__init__()
        self.parts, self.skip = [], 0

    def handle_starttag(self, tag, attrs):
        self.skip += tag in ("script", "style", "title")
        if tag in BLOCKS:
            self.parts.append("\n")

    def handle_endtag(self, tag):
        self.skip -= tag in ("script", "style", "title")
        if tag in BLOCKS:
            self.parts.append("\n")

    def handle_data(self, data):
        if not self.skip:
            self.parts.append(re.sub(r"\s+", " ", data))   # a newline in the source is a space on the screen


def visible_text(html: str) -> str:
    reader = _Text()
    reader.feed(html)
    return re.sub(r" *\n\s*", "\n", re.sub(r" +", " ", "".join(reader.parts)))


def gap_entry(name, rmse, gain, interval):
    return {"flight": name, "excluded": False,
            "mse": {"ukf": 2e-3, "knode-ukf": 1.5e-3},
            "gain_interval_pct": {"knode-ukf_vs_ukf": [1.1, 12.0]},
            "groups": {"ukf": {"p": 1e-4, "v": 2e-3, "a": 4e-3}, "knode-ukf": {"p": 1e-4, "v": 1e-3, "a": 3e-3}},
            "yardsticks": {"mocap_gaps": {"rmse_m": {"ukf": rmse, "knode-ukf": rmse * (1 - gain / 100)},
                                          "gain_pct": {"knode-ukf_vs_ukf": gain},
                                          "gain_interval_pct": {"knode-ukf_vs_ukf": interval},
                                          "gap_s": 0.5, "every_s": 2.5, "gaps": 3},
                           "fast_reference": {"velocity_rmse_m_s": {"ukf": 0.05}, "window_s": 0.05},
                           "paper_sg": {"mse": {"ukf": 2e-3, "knode-ukf": 1.5e-3}}}}


# flights: gains 12, 20, -8 (the last worse beyond its interval) on the mocap-gap yardstick
GAP_REPORT = {"model": "cf:2", "system": "crazyflie",
              "flights": [gap_entry("B2_circle_medium_rep1", 0.04, 12.0, [5.0, 19.0]),
                          gap_entry("B3_figure8_fast_rep2", 0.05, 20.0, [9.0, 30.0]),
                          gap_entry("ramp_low", 0.03, -8.0, [-14.0, -2.0])],
              "median": {"ukf": 2e-3, "knode-ukf": 1.5e-3}, "improvement_pct": {"knode-ukf_vs_ukf": 25.0},
              "headline": {"yardstick": "mocap_gaps", "median_gain_pct": {"knode-ukf_vs_ukf": 12.0},
                           "flights_better": {"knode-ukf_vs_ukf": 2},
                           "flights_worse_beyond_interval": {"knode-ukf_vs_ukf": 1},
                           "flights_better_beyond_interval": {"knode-ukf_vs_ukf": 2},
                           "flights_within_interval": {"knode-ukf_vs_ukf": 0},
                           "flights_undecided": {"knode-ukf_vs_ukf": 0}, "flights_scored": 3}}


def test_the_gap_headline_leads_when_the_report_has_it():
    head = evaluation_headline(GAP_REPORT)
    assert head["yardstick"] == "mocap_gaps"
    assert head["sentence"] == ("KNODE-UKF carried the estimate through mocap gaps 12.0 % better than its prior UKF "
                                "(median of 3 flights; flights from -8.0 % to +20.0 %): better on 2 of 3; of 3 "
                                "flights scored, worse beyond its 95 % interval on 1, better beyond it on 2, within "
                                "it on none, undecided (no interval) on none.")
    [pair] = head["pairs"]
    assert [r["flight"] for r in pair["rows"]] == ["B2_circle_medium_rep1", "B3_figure8_fast_rep2", "ramp_low"]


def test_without_gap_fields_the_headline_is_the_paper_mse_gain():
    report = {**GAP_REPORT, "headline": None,
              "flights": [{k: v for k, v in f.items() if k != "yardsticks"} for f in GAP_REPORT["flights"]]}
    head = evaluation_headline(report)
    assert head["yardstick"] == "paper_sg"
    # the per-flight gain is 100 (1 - 1.5 / 2) = 25 % on each flight; the median ratio of the report's medians
    assert [r["gain_pct"] for r in head["pairs"][0]["rows"]] == pytest.approx([25.0] * 3)
    assert head["sentence"].startswith("KNODE-UKF scored 25.0 % better than its prior UKF on the paper's "
                                       "Savitzky-Golay MSE (median of 3 flights")
    assert "worse beyond its 95 % interval on none, better beyond it on 3" in head["sentence"]


def test_the_cli_text_starts_with_the_same_sentence_as_the_page():
    text = format_report(GAP_REPORT)
    assert text.splitlines()[0] == evaluation_headline(GAP_REPORT)["sentence"]
    assert "ramp_low" in text and "WORSE beyond its interval" in text
    assert text.index("mocap gaps") < text.index("MSE over [p, v, a]")


def render_report(report: dict) -> str:
    head = evaluation_headline(report)
    return page("report.html", "Evaluation 1: model cf:2", evaluation=SimpleNamespace(id=1, job_id=2),
                report=report, head=head, gain_png=None, gap_methods=gap_methods(report),
                gap_settings={"gap_s": 0.5, "every_s": 2.5},
                methods=list(report["median"]), settings={"methods": ["ukf", "knode-ukf"], "horizon": 20,
                                                          "include_bad": False},
                sg_window=150, sg_window_used=151, paired=None, paired_png=None,
                scored=[(i + 1, f["flight"]) for i, f in enumerate(report["flights"])], chosen=None,
                chosen_entry=None, group="v", GROUPS=evaluation_plots.GROUPS, MSE_UNITS=evaluation_plots.MSE_UNITS,
                series={}, velocity={}, model_name="cf").body.decode()


def test_report_page_reads_answer_first_with_spaces_between_values_units_and_labels():
    html = render_report(GAP_REPORT)
    text = visible_text(html)
    body = text[text.index("Evaluation 1: model cf:2", text.index("learnest")):]
    first = body.splitlines()[1]
    assert first == evaluation_headline(GAP_REPORT)["sentence"]       # the answer is the first line under the title
    assert text.index("Per flight") < text.index("Details") < text.index("settings: methods")
    # the per-flight interval paragraph (under Details): flight, colon, method, interval, all spaced
    assert "B2_circle_medium_rep1: KNODE-UKF [+1.1, +12.0] %; B3_figure8_fast_rep2: KNODE-UKF" in text
    assert "+12.0 [+5.0, +19.0]" in text and "-8.0 [-14.0, -2.0]" in text      # the table's gain cells
    assert "Gaps of 0.5 s every 2.5 s." in text and "0.0400" in text     # gap settings, a gap RMSE in m
    for glued in (r"rep\dKNODE", r"\]%", r"%[A-Za-z]", r"m/s²[A-Za-z]", r"\d[A-Za-z]{3,}", r"[a-z]\.[A-Z]"):
        assert not re.search(glued, text), (glued, re.search(glued, text))


def test_diagnosis_page_states_its_split_and_spaces_units():
    report = {"system": "crazyflie", "split": "fit on the first 2 flight(s), scored on the other 2",
              "fitting_flights": ["a1", "a2"], "scored_flights": ["b1", "b2"],
              "prior": {"params": {"gamma": 0.42}},
              "effects": [{"id": "battery_thrust", "equation": "T = k v^gamma", "channel": "specific force",
                           "explained_fraction": 0.6, "params": {"gamma": 0.42, "bias_z": -0.0004362},
                           "units": {"gamma": "1", "bias_z": "m/s²"}, "ci95": {"gamma": [0.4, 0.44]},
                           "alternatives": [{"id": "acc_bias", "params": {"bias_z": -0.0004362},
                                             "units": {"bias_z": "m/s²"}, "fraction_of_chosen": 1.0,
                                             "delta_bic": 3.0}]}],
              "confounded": [], "before": {"specific_force_rmse": 0.5}, "after": {"specific_force_rmse": 0.4},
              "per_flight": [{"flight": "b1", "before": {"specific_force_rmse": 0.5},
                              "after": {"specific_force_rmse": 0.4}},
                             {"flight": "b2", "before": {"specific_force_rmse": 0.5},
                              "after": {"specific_force_rmse": 0.4}}],
              "improved_flights": {"specific_force_rmse": "2/2"}}
    flights = [(1, "a1"), (2, "a2"), (3, "b1"), (4, "b2")]
    html = page("diagnosis.html", "Diagnosis 1: crazyflie", diagnosis=SimpleNamespace(
        id=1, job_id=2, model_ref=None, settings={"methods": [], "epochs": 3}), report=report, flights=flights,
        headline=diagnosis_headline(report), split=diagnosis_split(report, [n for _, n in flights]), prior=[],
        summary="data:,", series=None, note=None, registered=None,
        how_much=lambda f: f"explains {100 * f:.0f} % as much",
        confounded_label=str, model_name=None).body.decode()
    text = visible_text(html)
    lines = text[text.index("Diagnosis 1: crazyflie", text.index("learnest")):].splitlines()
    assert lines[1] == ("Found battery_thrust; with it the specific force predicted from the inputs on the scored "
                        "flights is 20.0 % better (better on 2/2 flights).")
    assert lines[2].startswith("Split: fitted on a1, a2; scored on b1, b2 (fit on the first 2 flight(s)")
    assert "bias_z = -0.0004362 m/s² explains 100 % as much" in text
    assert "gamma\n0.42\n[0.4, 0.44]\n" in text and "0.42 1" not in text


def test_the_diagnose_form_checks_its_fields_as_the_api_does(tmp_path):
    from utils.service import running_app

    with running_app(tmp_path / "home") as client:
        none = client.post("/ui/diagnoses", data={"methods": ["ukf"]})
        assert none.status_code == 422 and "choose the flight(s) to diagnose" in none.text
        nameless = client.post("/ui/diagnoses", data={"flights": ["1"], "methods": ["ukf"], "register": "on"})
        assert nameless.status_code == 422 and "give the model name" in nameless.text
        missing = client.post("/ui/diagnoses", data={"flights": ["7"], "methods": ["ukf"]})
        assert missing.status_code == 404 and "flight(s) not found: 7" in missing.text
        bad_name = client.post("/ui/diagnoses", data={"flights": ["7"], "methods": ["ukf"], "register": "on",
                                                      "register_as": "no spaces allowed"})
        assert bad_name.status_code == 422 and "register" in bad_name.text


def test_the_gain_figure_labels_each_flight_and_uses_the_method_colour():
    from matplotlib.colors import to_hex

    from learnest.service.local.figures import evaluation_summary, gain_per_flight
    from learnest.service.local.palette import METHOD_COLOURS

    head = evaluation_headline(GAP_REPORT)
    [ax] = gain_per_flight(head).axes
    assert [t.get_text() for t in ax.get_yticklabels()] == ["B2_circle_medium_rep1", "B3_figure8_fast_rep2", "ramp_low"]
    [legend] = [t.get_text() for t in ax.get_legend().get_texts()]
    assert legend.startswith("KNODE-UKF vs UKF") and "median +12.0 %" in legend
    dots = [line for line in ax.get_lines() if line.get_marker() == "o" and len(line.get_xdata()) == 1]
    assert sorted(float(d.get_xdata()[0]) for d in dots) == [-8.0, 12.0, 20.0]
    assert {to_hex(d.get_color()) for d in dots} == {METHOD_COLOURS["knode-ukf"]}
    # the CLI's --plot: the same gain panel above the paired MSE dots
    figure = evaluation_summary(GAP_REPORT)
    assert len(figure.subfigs) == 2 and len(figure.subfigs[0].axes) == 1 and len(figure.subfigs[1].axes) == 1


def _undecided_report() -> dict:
    """GAP_REPORT with a flight of one gap (a gain, no interval) and one too short for a gap, its headline
    built by the evaluation's own `estimators.headline.headline`."""
    from learnest.estimators.headline import headline

    one_gap = gap_entry("trefoil_one_gap", 0.06, -25.0, None)
    one_gap["yardsticks"]["mocap_gaps"]["gaps"] = 1
    short = gap_entry("hover_short", 0.02, 0.0, None)
    short["yardsticks"]["mocap_gaps"] = {"rmse_m": {}, "gain_pct": {}, "gain_interval_pct": {}, "gaps": 0,
                                         "gap_s": 0.5, "every_s": 2.5,
                                         "skipped": "the kept flight is 4.0 s long, too short for one mocap gap"}
    flights = GAP_REPORT["flights"] + [one_gap, short]
    return {**GAP_REPORT, "flights": flights, "headline": headline(flights).to_dict()}


def test_a_flight_without_an_interval_is_counted_undecided_on_every_surface():
    """The headline's four counts add up to the flights scored in the JSON, the sentence, the CLI text and
    the page; the undecided flights are named with why."""
    report = _undecided_report()
    given = report["headline"]
    key = "knode-ukf_vs_ukf"
    assert given["flights_scored"] == 5
    assert (given["flights_better_beyond_interval"][key], given["flights_worse_beyond_interval"][key],
            given["flights_within_interval"][key], given["flights_undecided"][key]) == (2, 1, 0, 2)
    head = evaluation_headline(report)
    assert head["sentence"].endswith("better on 2 of 4; of 5 flights scored, worse beyond its 95 % interval on 1, "
                                     "better beyond it on 2, within it on none, undecided (no interval) on 2.")
    text = format_report(report)
    assert text.splitlines()[0] == head["sentence"]
    assert "undecided on 2 of 5 flights scored: trefoil_one_gap: one gap: an interval needs two; hover_short: " \
           "the kept flight is 4.0 s long" in text
    assert ("better beyond it on 2, within it on 0, undecided (no interval) on 2 of 5 flights scored" in text)
    assert "-25.0 % [no interval]" in text
    page_text = visible_text(render_report(report))
    assert head["sentence"] in page_text
    assert "-25.0 undecided (no interval)" in page_text
    assert "better on 2, worse on 1, within on 0, undecided on 2 of 5 scored" in page_text


def test_a_report_stored_before_the_four_counts_is_told_from_its_intervals():
    """An older report's headline has no undecided count: the page tells it from the flights' intervals."""
    report = _undecided_report()
    old = {k: v for k, v in report["headline"].items()
           if k not in ("flights_better_beyond_interval", "flights_within_interval", "flights_undecided",
                        "flights_undecided_names", "flights_scored")}
    pair = evaluation_headline({**report, "headline": old})["pairs"][0]
    assert (pair["better_beyond_interval"], pair["worse_beyond_interval"], pair["within_interval"],
            pair["undecided"], pair["scored"]) == (2, 1, 0, 2, 5)


def test_the_headline_says_which_noise_each_side_ran_with():
    """A report that names its noise (`noise` {method: source}) says it after the gain, like with like or not."""
    identified = evaluation_headline({**GAP_REPORT, "noise": {"ukf": "identified", "knode-ukf": "identified"}})
    assert identified["sentence"].endswith("Each ran with its own noise, identified on the training flights.")
    paper = evaluation_headline({**GAP_REPORT, "noise": {"ukf": "paper", "knode-ukf": "paper"}})
    assert paper["sentence"].endswith("Both ran with the system's fixed noise (the paper's).")
    mixed = evaluation_headline({**GAP_REPORT, "noise": {"ukf": "paper", "knode-ukf": "identified"}})
    assert mixed["sentence"].endswith("Noise: KNODE-UKF identified, UKF paper: not tuned the same way, so not like "
                                      "with like.")
    assert evaluation_headline(GAP_REPORT)["sentence"].endswith("undecided (no interval) on none.")
