"""Argument types and output helpers shared by the ``appliance`` subcommands (not a command itself)."""
from __future__ import annotations

import argparse
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Callable, Iterator

from appliance.errors import InputDataError
from drivers.biplane_folder import PLANES


def positive_float(text: str) -> float:
    """argparse type: a number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def non_negative_float(text: str) -> float:
    """argparse type: a finite number >= 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (value >= 0.0 and value != float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def integer_at_least(minimum: int) -> Callable[[str], int]:
    """argparse type factory: a whole number >= ``minimum``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        return value
    return parse


#: argparse type: a whole number >= 1.
count = integer_at_least(1)


@contextmanager
def output_stream(path: Path | None, what: str) -> Iterator[IO[str]]:
    """Yield stdout, or ``path`` opened for writing; ``what`` names the content in the error message."""
    if path is None:
        yield sys.stdout
        return
    try:
        stream = path.open("w", encoding="utf-8")
    except OSError as err:
        raise InputDataError(f"{path}: cannot write the {what} ({err.strerror or err})") from err
    with stream:
        yield stream


def prepare_frame_folder(out: Path) -> Path:
    """Create ``out`` for a new biplane frame folder; refuse a file or a folder that already holds frames."""
    if out.exists() and not out.is_dir():
        raise InputDataError(f"{out}: exists and is not a folder")
    for plane in PLANES:
        if (out / plane).is_dir() and any((out / plane).iterdir()):
            raise InputDataError(f"{out}: already holds frames in {plane}/; choose a new or empty folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputDataError(f"{out}: cannot create the folder ({err.strerror or err})") from err
    return out
