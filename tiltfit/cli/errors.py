"""What every `tiltfit` command says to its user: the one-line error (`CliError`, `tiltfit: <file>: <problem>`),
library messages put in command-line terms, progress on stderr, and the checks of output paths and numbers made
before any work."""
from __future__ import annotations

import math
import re
import sys

from camio.files import output_problem


class CliError(Exception):
    """A user-facing failure: `tiltfit: <file>: <problem>`."""

    def __init__(self, file: str, problem: str):
        super().__init__(f"{file}: {problem}")
        self.file, self.problem = file, problem


#: The library's names for what the command line calls an option (library messages speak in API terms).
_API_TO_OPTION = {"as the pixel_pitch_mm argument": "as --pixel-pitch-mm"}


def in_cli_terms(msg: str) -> str:
    """A library message with its API names replaced by the command-line options they come from."""
    for api, option in _API_TO_OPTION.items():
        msg = msg.replace(api, option)
    return msg


def as_cli_error(file: str, err: Exception) -> CliError:
    """Wrap an exception whose message may already start with the file name (one line, in command-line
    terms)."""
    msg = in_cli_terms("; ".join(line.strip() for line in str(err).strip().splitlines()) or type(err).__name__)
    prefix = f"{file}: "
    if msg.startswith(prefix):
        return CliError(file, msg[len(prefix):])
    located = re.match(rf"{re.escape(file)}(:\d+:\d+): (.*)", msg)
    if located:  # a parser's `FILE:LINE:COL: problem`, named once as the renderer writes it
        return CliError(file + located[1], located[2])
    return CliError(file, msg)


def progress_printer(quiet: bool):
    """say(line): the line on stderr, unless `quiet` (-q)."""
    def say(line: str):
        if not quiet:
            print(line, file=sys.stderr, flush=True)

    return say


def check_output(path: str) -> None:
    """Refuse, before any work, an output path that cannot be written (`camio.files.output_problem`)."""
    problem = output_problem(path)
    if problem:
        raise CliError(path, problem)


def check_range(option: str, value, low_exclusive: float, high: float, what: str) -> None:
    """Refuse a number of `option` outside (low_exclusive, high]: beyond its stated range it is a unit mistake."""
    if not (math.isfinite(value) and low_exclusive < value <= high):
        raise CliError(option, f"expected {what} in ({low_exclusive:g}, {high:g}], got {value}")
