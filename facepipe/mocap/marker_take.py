"""A marker take read and prepared for replay: the steps ``facepipe replay`` and each take of
``facepipe batch`` share, so the two cannot drift apart (the batch promises a serial replay's
outputs to the bit).

Read in the rig's units (absent markers are filled through the prior when cleaning, an error
without it), with the neutral take read the same way, then aligned, stabilised and cleaned
window by window (:func:`facepipe.mocap.prepare.prepare_take_windows`; the windows are cleaned
as the replay takes them).
"""

from __future__ import annotations

from dataclasses import dataclass

from facepipe.mocap.cleaning import CleanOptions
from facepipe.mocap.prepare import PrepareOptions, PreparedTake, prepare_take_windows
from facepipe.mocap.registry import read_take
from facepipe.mocap.take import Take, parse_frame_slice


@dataclass(frozen=True)
class MarkerTakeOptions:
    """replay's options for reading and preparing a marker take (their defaults are replay's)."""

    take_units: str | None = None
    subject: str | None = None
    clean: bool = True
    stabilise: bool = True
    neutral_frame: int | None = None
    neutral_take: str | None = None  # a path
    frames: str | None = None  # rows "A:B"
    smooth: float = 0.0


@dataclass(frozen=True)
class MarkerTake:
    """``take``: the rows replayed (its frames and times); ``prepared``: their clean windows."""

    path: str
    take: Take
    prepared: PreparedTake

    def report(self) -> dict:
        """The take's part of replay.json (once every window is cleaned: each is cleaned once)."""
        gaps = self.prepared.report()
        return {"take": self.path, "mocap": gaps, "markers": gaps["markers"], "extra_markers": self.take.extra_markers}


def read_marker_take(path, model, options: MarkerTakeOptions) -> MarkerTake:
    """Read the take at ``path`` for ``model`` and prepare it (its windows are cleaned lazily)."""
    read = dict(units=model.meta.get("units"), take_units=options.take_units, subject=options.subject,
                absent="missing" if options.clean else "error", allow_empty_frames=True)
    take = read_take(path, model.marker_names, **read)
    neutral = read_take(options.neutral_take, model.marker_names, **read) if options.neutral_take else None
    prepare = PrepareOptions(neutral_frame=options.neutral_frame, neutral_take=neutral, stabilise=options.stabilise,
                             clean=options.clean, frames=parse_frame_slice(options.frames) if options.frames else None,
                             clean_options=CleanOptions(smooth=options.smooth))
    prepared = prepare_take_windows(take, model, prepare)
    return MarkerTake(str(path), take if prepare.frames is None else take.select(prepare.frames), prepared)
