"""Progress of a long CLI command on stderr: a bar on a terminal, one plain line per stage otherwise.

A job reports a fraction (0..1, the job row's ``progress``) and a stage ("epoch 12/150", "knode-ukf on
flight3 (2/4)") with the seconds left.  `StageProgress` shows both from the same report, so the bar and its
label never disagree: the fraction is clamped to 0..1 and never goes back (a bar never shows 133 % or
jumps back), and the bar's count is derived from the fraction, never counted separately.  When stderr is
not a terminal (piped into a file, a CI log) there is no bar and no carriage return: each new stage is
one line, "learnest: training demo: epoch 12/150 (8 %)".
"""
from __future__ import annotations

import sys
from typing import IO


def is_terminal(stream: IO[str]) -> bool:
    """Whether ``stream`` is an interactive terminal (a bar can redraw itself there)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):   # closed, or a stream without isatty
        return False


class StageProgress:
    """One command's progress: ``update(fraction, stage, seconds_left)``; a context manager.

    Parameters
    ----------
    label : str
        What runs ("training demo", "evaluating").
    stream : file, optional
        Default sys.stderr.
    bar : bool, optional
        Draw a tqdm bar; default: when ``stream`` is a terminal.
    """

    BAR_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| [{elapsed}{postfix}]"
    STEPS = 1000   # the bar's resolution: its count is round(fraction * STEPS)

    def __init__(self, label: str, stream: IO[str] | None = None, bar: bool | None = None):
        self.label, self.stream = label, stream or sys.stderr
        self.fraction = 0.0
        self.stage: str | None = None
        self._printed: str | None = None
        self._bar = None
        if is_terminal(self.stream) if bar is None else bar:
            from tqdm import tqdm

            self._bar = tqdm(total=self.STEPS, desc=label, file=self.stream, bar_format=self.BAR_FORMAT)

    @property
    def draws_bar(self) -> bool:
        """Whether a bar is drawn (else each new stage is one plain line)."""
        return self._bar is not None

    def __enter__(self) -> StageProgress:
        return self

    def __exit__(self, kind, _value, _traceback) -> None:
        self.close(done=kind is None)

    def update(self, fraction: float | None = None, stage: str | None = None,
               seconds_left: float | None = None) -> None:
        """Show a new fraction (clamped to 0..1, never lower than before) and/or stage."""
        if fraction is not None:
            self.fraction = max(self.fraction, min(1.0, max(0.0, float(fraction))))
        if stage is not None:
            self.stage = stage
        left = f", about {seconds_left:.0f} s left" if seconds_left is not None else ""
        if self._bar is not None:
            self._bar.n = round(self.fraction * self.STEPS)
            self._bar.set_postfix_str(f"{self.stage}{left}" if self.stage else left.lstrip(", "), refresh=False)
            self._bar.refresh()
        elif stage is not None and stage != self._printed:   # one line per stage, never per tick
            self._printed = stage
            print(f"learnest: {self.label}: {stage} ({100 * self.fraction:.0f} %{left})", file=self.stream,
                  flush=True)

    # the callbacks the service functions take (service.local calls both from one poll of the
    # job row: the fraction is kept and drawn with the stage that comes with it, never alone)
    def progress(self, fraction: float) -> None:
        """``progress(fraction)`` callback: kept, shown by the next ``on_stage`` (or `close`)."""
        self.fraction = max(self.fraction, min(1.0, max(0.0, float(fraction))))

    def on_stage(self, stage: str, seconds_left: float | None = None) -> None:
        """``on_stage(stage, seconds_left)`` callback."""
        self.update(stage=stage, seconds_left=seconds_left)

    def close(self, done: bool = True) -> None:
        """Finish: a finished command's bar shows 100 %; an interrupted one stays where it was."""
        if done:
            self.update(1.0)
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        elif done and self._printed is not None:
            print(f"learnest: {self.label}: done", file=self.stream, flush=True)
