"""The errors `renderer` raises for bad input, each with a one-line message that names the file or field.

They live here, below every other module, so that the library, the command line (`renderer.cli`) and its
back ends (`renderer.backends`) share them without importing each other. The old places still export them:
`renderer.params.SceneError`, `renderer.io.ImageIOError`, `renderer.cli.UsageError`.
"""
from __future__ import annotations


class SceneError(ValueError):
    """A bad scene description; the message is one line naming the field."""


class ImageIOError(ValueError):
    """An image that cannot be read or written; one-line message naming the file."""


class UsageError(Exception):
    """A bad command-line value that argparse cannot check by itself (one-line message)."""
