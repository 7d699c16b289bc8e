"""One error type for bad input, and the command-line wrapper that turns it into one line.

Every command ends a bad input (missing or corrupt file, wrong depth scale, empty box, NaN pose,
malformed document) with ``error: <file>: <problem>`` on stderr and exit code 2.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable, NoReturn


class InputError(Exception):
    """Bad input from the user: names the file and the problem in one line."""

    def __init__(self, path: str | Path | None, problem: str) -> None:
        self.path = None if path is None else str(path)
        self.problem = " ".join(str(problem).split())  # always one line
        super().__init__(str(self))

    def __str__(self) -> str:
        return f"{self.path}: {self.problem}" if self.path else self.problem


EXIT_BAD_INPUT = 2


def fail(error: InputError) -> NoReturn:
    """Print the one-line error and exit with code 2."""
    print(f"error: {error}", file=sys.stderr)
    sys.exit(EXIT_BAD_INPUT)


def run_cli(main: Callable[[list[str] | None], int | None], argv: list[str] | None = None) -> int:
    """Run a command's main function, turning InputError into a one-line message and exit 2."""
    try:
        code = main(argv)
    except InputError as error:
        fail(error)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return int(code or 0)
