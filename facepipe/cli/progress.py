"""Progress for steps of unequal length, honest about what it can tell.

A frame bar's ETA is only as good as its rate, so a bar must not start before its frames do:
:class:`LazyBar` opens when the first frames are done (set-up and cleaning before them do not
drag its rate down and its ETA up). Steps of unlike length (reading a rig, factorising the shell,
fitting the basis) get a :class:`StageBar`: which step is running, how many are done and the time
spent, never an ETA extrapolated from unlike steps.
"""

from __future__ import annotations

import sys

from tqdm import tqdm

STAGE_FORMAT = "{desc}: {n_fmt}/{total_fmt} steps [{elapsed}]{postfix}"

#: seconds between a bar's redraws where stderr is a file or pipe (a batch job's log, CI): tqdm's
#: 0.1 s would write ten carriage-return updates a second into the log
LOG_REFRESH_SECONDS = 10.0


def refresh_seconds(stream=None) -> float:
    """How often a bar on ``stream`` (stderr by default) redraws: tqdm's default on a terminal,
    :data:`LOG_REFRESH_SECONDS` elsewhere (the first and last lines are always written)."""
    stream = sys.stderr if stream is None else stream
    try:
        interactive = stream.isatty()
    except (AttributeError, ValueError):  # a closed or file-like stream without isatty
        interactive = False
    return 0.1 if interactive else LOG_REFRESH_SECONDS


class StageBar:
    """A bar counting named steps: ``step("factorising the shell")`` marks the previous step done
    and names the running one. Nothing is shown when ``quiet``. Closing twice is harmless: a bar
    whose last step's work is known to be over closes at once (:meth:`close_after_last_step`),
    before another bar opens below it."""

    def __init__(self, total: int, desc: str, quiet: bool = False):
        self._bar = tqdm(total=total, desc=desc, bar_format=STAGE_FORMAT, disable=quiet, file=sys.stderr,
                         dynamic_ncols=True, mininterval=refresh_seconds())
        self._total = total
        self._started = 0  # steps started (tqdm's count stays 0 on a disabled bar)
        self._closed = False

    def step(self, name: str) -> None:
        if self._started:
            self._bar.update(1)
        self._started += 1
        self._bar.set_postfix_str(name)

    def close_after_last_step(self) -> None:
        """Close the bar if its last step has started: the caller knows that step's work is over
        (e.g. the frames it prepared are being used)."""
        if self._started >= self._total > 0:
            self.close()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._started and self._bar.n < self._bar.total:
            self._bar.update(self._bar.total - self._bar.n)
        self._bar.set_postfix_str("done", refresh=False)  # drawn once, by close
        self._bar.close()

    def __enter__(self):
        return self

    def __exit__(self, kind, value, tb):
        if kind is None:
            self.close()
        elif not self._closed:  # an error: leave the bar where it stopped
            self._closed = True
            self._bar.close()


class LazyBar:
    """A frame bar opened at its first update (``make()`` makes the tqdm bar then)."""

    def __init__(self, make):
        self._make = make
        self._bar = None

    def update(self, n: int = 1) -> None:
        if self._bar is None:
            self._bar = self._make()
        self._bar.update(n)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
