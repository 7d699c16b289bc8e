"""One writer per document: a lock file beside it, and a check that the file is still the one that was read.

``DocumentLock(path)`` creates ``<document>.lock`` holding its owner (host, pid, start time, tool) and takes an
exclusive ``flock`` on it for as long as it is held. The kernel drops the flock when the owner dies, so a lock
left by a killed process is stale by construction: the next writer takes it over. A second writer while the
owner lives gets :class:`DocumentLocked`, a one-line InputError naming the holder.

``fingerprint(path)`` is the SHA-256 of a file's bytes (None when absent); a writer compares the fingerprint of
what it read with the file's just before replacing it (:func:`check_unchanged`), and refuses to overwrite a
change it did not make.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import socket
import time
from pathlib import Path

from .errors import InputError


class DocumentLocked(InputError):
    """Another live process holds the document's lock."""


def lock_path(document: str | Path) -> Path:
    document = Path(document)
    return document.with_name(document.name + ".lock")


def _holder_text(path: Path) -> str:
    try:
        owner = json.loads(path.read_text())
        since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(float(owner["started"])))
        return f"{owner.get('tool', 'a writer')} (pid {int(owner['pid'])} on {owner['host']}, since {since})"
    except (OSError, ValueError, KeyError, TypeError):
        return "another process"


class DocumentLock:
    """The lock of one document (see the module notes); a context manager. ``tool`` names the holder in messages."""

    def __init__(self, document: str | Path, tool: str) -> None:
        self.document = Path(document)
        self.path = lock_path(self.document)
        self.tool = tool
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> "DocumentLock":
        """Take the lock, or raise DocumentLocked naming the live holder (InputError if the folder is not writable)."""
        if self._fd is not None:
            return self
        for _ in range(10):  # retried only when the file is replaced under us
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
            except OSError as error:
                raise InputError(self.path, f"cannot create the document's lock file ({error.strerror})") from error
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as error:
                os.close(fd)
                if error.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise DocumentLocked(self.document, f"is open for writing by {_holder_text(self.path)}; "
                                                        "close that first (nothing was changed)") from None
                raise InputError(self.path, f"cannot lock the document ({error.strerror})") from error
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if not same:  # the previous holder removed the file between our open and our lock: start again
                os.close(fd)
                continue
            owner = {"host": socket.gethostname(), "pid": os.getpid(), "started": time.time(), "tool": self.tool}
            os.ftruncate(fd, 0)
            os.write(fd, json.dumps(owner).encode())
            self._fd = fd
            return self
        raise InputError(self.path, "the lock file keeps changing; another writer is starting and stopping")

    def release(self) -> None:
        """Give the lock up and remove the file (a waiting writer re-checks the file it locked)."""
        if self._fd is None:
            return
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass
        finally:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> "DocumentLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def fingerprint(path: str | Path) -> str | None:
    """SHA-256 of the file's bytes, or None when it does not exist."""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except FileNotFoundError:
        return None


def check_unchanged(path: str | Path, expected: str | None) -> None:
    """Raise InputError unless the file's fingerprint is still ``expected`` (None: it must still be absent)."""
    now = fingerprint(path)
    if now != expected:
        what = "was created" if expected is None else "was deleted" if now is None else "was changed"
        raise InputError(path, f"{what} on disk by another program since it was read; not overwriting it")
