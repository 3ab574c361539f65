"""Progress shown by the CLI (service.cli.progress.StageProgress): never above 100 %, never back, label and bar
from the same report, and one plain line per stage when stderr is not a terminal."""
from __future__ import annotations

import io
import re
import warnings

from learnest.service.cli.progress import StageProgress


def test_a_bar_never_exceeds_100_percent_nor_goes_back():
    out = io.StringIO()
    with warnings.catch_warnings():
        warnings.simplefilter("error")        # tqdm's "clamping frac" TqdmWarning would fail here
        with StageProgress("evaluating", stream=out, bar=True) as bar:
            shown = []
            for fraction in (0.0, 0.33, 0.66, 1.0, 1.33, 0.5, -1.0):   # a job reporting past the end, and back
                bar.update(fraction, f"{fraction}")
                shown.append(bar._bar.n)
    assert shown == [0, 330, 660, 1000, 1000, 1000, 1000]
    percentages = [int(p) for p in re.findall(r"(\d+)%\|", out.getvalue())]
    assert percentages and max(percentages) == 100 and percentages == sorted(percentages)


def test_a_fraction_alone_waits_for_its_stage():
    out = io.StringIO()
    with StageProgress("training demo", stream=out, bar=True) as bar:
        bar.on_stage("epoch 1/150")
        before = out.getvalue()
        bar.progress(0.5)                  # drawn only with the stage read from the same job row
        assert out.getvalue() == before
        bar.on_stage("epoch 75/150")
        assert re.search(r"50%\|.*epoch 75/150", out.getvalue().split("\r")[-1])


def test_the_label_and_the_bar_come_from_the_same_report():
    out = io.StringIO()
    with StageProgress("training demo", stream=out, bar=True) as bar:
        epochs = 150
        for epoch in range(epochs):
            bar.update(0.02 + 0.97 * (epoch + 1) / epochs, f"epoch {epoch + 1}/{epochs}")
            frames = out.getvalue().split("\r")
            last = frames[-1]
            percent, label = int(re.search(r"(\d+)%\|", last).group(1)), re.search(r"epoch (\d+)/150", last)
            assert int(label.group(1)) == epoch + 1
            assert abs(percent - round(100 * (0.02 + 0.97 * (epoch + 1) / epochs))) <= 1


def test_not_a_terminal_gives_one_line_per_stage_and_no_carriage_return():
    out = io.StringIO()     # StringIO.isatty() is False: as when stderr is piped into a file
    with StageProgress("diagnosing", stream=out) as bar:
        for k in range(200):
            bar.update(k / 200, "fitting effects" if k < 100 else "scoring 1/1 flight(s)")
    text = out.getvalue()
    assert "\r" not in text
    assert text.splitlines() == ["learnest: diagnosing: fitting effects (0 %)",
                                 "learnest: diagnosing: scoring 1/1 flight(s) (50 %)",
                                 "learnest: diagnosing: done"]
