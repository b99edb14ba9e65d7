"""Errors a user can act on."""

from __future__ import annotations


class IngestError(Exception):
    """A file cannot be read as the requested or detected format.

    The message names the file and what was expected; the CLI prints it and exits with code 2.
    """

    def __init__(self, path: str, message: str) -> None:
        super().__init__(f"{path}: {message}")
        self.path = path
        self.message = message
