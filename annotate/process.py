"""The browser tool as a child process: start ``annotate SEQ ...``, wait for what it prints, stop it.

For programs that drive the tool from outside (the browser tests, the annotator benchmark, a script). The child's
output goes to a log file, not a pipe: nobody reads a pipe while the server runs, and a full one would block it.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: What the tool prints once it serves: the page's address (with its token beyond loopback).
URL_PATTERN = r"open (http://\S+)"


class AnnotateProcess:
    """``annotate ARGS`` in a child process, its output in ``log``. ``environment``: variables set for the child
    (e.g. REDWOOD_GT_ENGINE)."""

    def __init__(self, args: list[str], log: Path, environment: dict[str, str] | None = None) -> None:
        self.log = Path(log)
        env = {**os.environ, **(environment or {})}
        with open(self.log, "w") as out:  # the child holds its own copy
            self.process = subprocess.Popen([sys.executable, "-c", "from annotate.cli import entry; entry()", *map(str, args)],
                                            cwd=REPO, stdout=out, stderr=subprocess.STDOUT, text=True, env=env)

    def printed(self, pattern: str = URL_PATTERN, timeout: float = 120.0) -> re.Match:
        """The first match of ``pattern`` in the child's output, waiting up to ``timeout`` seconds; RuntimeError with
        the output when the child exits or the time runs out first."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self.process.poll() is None:
            match = re.search(pattern, self.log.read_text())
            if match:
                return match
            time.sleep(0.2)
        raise RuntimeError(f"annotate did not print {pattern!r}:\n{self.log.read_text()}")

    def stop(self) -> None:
        """Terminate the child (kill it after 10 s) and wait for it."""
        self.process.terminate()
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


def start(args: list[str], log: Path, timeout: float = 120.0, environment: dict[str, str] | None = None) -> tuple[AnnotateProcess, str]:
    """``annotate ARGS`` started and serving: the process and the URL it printed (stopped again when it prints none)."""
    child = AnnotateProcess(args, log, environment)
    try:
        return child, child.printed(URL_PATTERN, timeout).group(1)
    except BaseException:  # no URL, or an interrupt while waiting: the child must not outlive the caller
        child.stop()
        raise
