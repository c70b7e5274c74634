"""argparse types for the commands' numeric options: a value out of range is a usage error naming the option
(exit 2, one line) before any work, not an internal error part-way through it."""

from __future__ import annotations

import argparse
from collections.abc import Callable


def int_at_least(low: int, high: int | None = None) -> Callable[[str], int]:
    """An integer >= low (and <= high, when given)."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if v < low:
            raise argparse.ArgumentTypeError(f"must be at least {low}, got {v}")
        if high is not None and v > high:
            raise argparse.ArgumentTypeError(f"must be at most {high}, got {v}")
        return v
    parse.__name__ = f"integer >= {low}"  # what argparse names in its "invalid ... value" message
    return parse


positive_int = int_at_least(1)


def positive_float(text: str) -> float:
    """A finite number > 0."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0 < v < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return v


positive_float.__name__ = "positive number"


def positive_float_up_to(high: float) -> Callable[[str], float]:
    """A finite number > 0 and <= high."""
    def parse(text: str) -> float:
        v = positive_float(text)
        if v > high:
            raise argparse.ArgumentTypeError(f"must be at most {high:g}, got {text}")
        return v
    parse.__name__ = f"positive number up to {high:g}"
    return parse


MAX_SECONDS = 1e7  # 115 days: longer than any recording; its nanoseconds fit an int64 with room to spare


def seconds_from_start(text: str) -> float:
    """A time in a recording, in seconds from its start: finite, 0 .. MAX_SECONDS (nan ended `vio calib imu-noise
    --start` in an internal error, 1e300 in an OverflowError; -5 was taken as 0, unsaid)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not 0 <= v <= MAX_SECONDS:
        raise argparse.ArgumentTypeError(f"must be seconds from the recording's start, 0 to {MAX_SECONDS:g}, got "
                                         f"{text}")
    return v


seconds_from_start.__name__ = "seconds from the start"


def path_arg(text: str) -> str:
    """A file or folder named on the command line: not empty. An empty one (a shell variable not set) was read as
    not given (`vio replay D -o ""` wrote no trajectory, exit 0; `--calibration ""` flew the dataset's own) or as
    the working folder (`vio simulate ""` wrote a dataset into it) (a review's finding)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path (a shell variable not set?)")
    return text


path_arg.__name__ = "path"


def url_arg(text: str) -> str:
    """A connection or viewer named on the command line: not empty (`--mavlink "$FC"` with FC unset replayed without
    sending anything, exit 0; `--view ""` showed nothing)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty (a shell variable not set?)")
    return text


url_arg.__name__ = "url"


def topic_arg(text: str) -> str:
    """A bag topic named on the command line: not empty (`--left-topic "$T"` with T unset read the [bag] default,
    unsaid)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty (a shell variable not set?)")
    return text


topic_arg.__name__ = "topic"
