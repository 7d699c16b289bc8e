"""Atomic file writes: write to a temporary name in the same folder, fsync, rename.

A kill at any moment leaves either the old file or the new one, never a torn one. Files get the mode a plain
``open()`` would give them (0666 less the user's umask), not the 0600 of a temporary file.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path


def _read_umask() -> int:
    mask = os.umask(0o022)  # reading the umask sets it: put it back at once (before any thread starts writing)
    os.umask(mask)
    return mask


#: The mode of new files (0666 less the umask), read once at import.
FILE_MODE = 0o666 & ~_read_umask()


def write_bytes_atomic(path: str | Path, data: bytes, backup: bool = False) -> Path:
    """Write ``data`` to ``path`` atomically; with ``backup`` keep the previous version as ``path.bak``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, FILE_MODE)
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        if backup and path.exists():
            # copy, not rename: the live file must exist at every moment; the copy goes to a
            # temporary name first so that a kill mid-copy cannot leave a torn backup either
            fd_bak, tmp_bak = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".bak.tmp", dir=path.parent)
            os.close(fd_bak)
            try:
                shutil.copy2(path, tmp_bak)
                os.replace(tmp_bak, path.with_name(path.name + ".bak"))
            except BaseException:
                try:
                    os.unlink(tmp_bak)
                except FileNotFoundError:
                    pass
                raise
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def write_text_atomic(path: str | Path, text: str, backup: bool = False) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically (see :func:`write_bytes_atomic`)."""
    return write_bytes_atomic(path, text.encode("utf-8"), backup=backup)


def temporary_sibling(path: str | Path) -> Path:
    """A fresh temporary path next to ``path`` (for writers that need a file name, e.g. PNG, OBJ)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.fchmod(fd, FILE_MODE)
    os.close(fd)
    return Path(tmp)
