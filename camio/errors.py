"""The errors raised for bad input, each with a one-line message that names the file or field, and the one
way an exception becomes that line (`one_line`).

They live here, below `renderer` and `tiltfit`, so that the libraries, the two commands and the renderer's back
ends share them without importing each other. `renderer.core.params.SceneError`, `camio.files.ImageIOError` and
`renderer.cli.main.UsageError` are the same classes.
"""
from __future__ import annotations


class SceneError(ValueError):
    """A bad scene description; the message is one line naming the field."""


class ImageIOError(ValueError):
    """An image that cannot be read or written; one-line message naming the file."""


class UsageError(Exception):
    """A bad command-line value that argparse cannot check by itself (one-line message)."""


def one_line(e) -> str:
    """An exception or a message as one line: an OSError as `FILE: reason`, anything else (a message: a str, None
    as "") with its whitespace collapsed. The one way a message is flattened for stderr and for image metadata."""
    if isinstance(e, OSError) and e.filename is not None and e.strerror:
        return f"{e.filename}: {e.strerror}"
    return " ".join(str("" if e is None else e).split())


def os_reason(e: OSError) -> str:
    """Why an OSError happened, without its file (for messages that name the file themselves): its strerror
    ("Permission denied"), else the exception as one line."""
    return e.strerror or one_line(e)
