"""Errors that the command line reports as one line, naming the file (and line) at fault."""
from __future__ import annotations

import re
from os import PathLike

# "OpenCV(5.0.0) /path/bitstrm.cpp:59: error: (-2:Unspecified error) Unexpected end of input stream in
# function 'readBlock'" -> "Unexpected end of input stream"
_CV_ERROR = re.compile(r"error: \([^)]*\)\s*(.*?)(?: in function .*)?$")


def opencv_words(text: str) -> str:
    """OpenCV's own words in one of its error lines, without its version, source path, error code and
    function; ``text`` itself when it is no such line."""
    m = _CV_ERROR.search(text)
    return m.group(1) if m else text


class CpdetectError(Exception):
    """A problem with the user's input or request, reported without a traceback.

    ``path`` and ``line`` (1-based) locate the problem; ``exit_code`` is what the CLI returns.
    """

    def __init__(self, message: str, path: str | PathLike | None = None, line: int | None = None,
                 exit_code: int = 2):
        self.message = message
        self.path = None if path is None else str(path)
        self.line = line
        self.exit_code = exit_code
        super().__init__(str(self))

    def __str__(self) -> str:
        where = ""
        if self.path is not None:
            where = self.path if self.line is None else f"{self.path}:{self.line}"
            where += ": "
        return where + self.message


class InputError(CpdetectError):
    """Unreadable, malformed or inconsistent input data (exit code 2)."""


class UsageError(CpdetectError):
    """A request that cannot be honoured as asked: unknown detector, bad setting (exit code 2)."""
