"""Whole exports or none: one sequence's files swapped into an export folder as one unit, with recovery.

An export of sequence S into OUT replaces several files (``S.obj``, ``masks/S/``, ``reports/S.json|png``)
and one shared file, ``annotations.json``, the commit point. :class:`ExportTransaction`:

1. stages every new file in ``OUT/.staging-S-<id>/`` (nothing of OUT touched; a kill leaves only that folder),
   without OUT's lock: the staging is claimed by an ``flock`` on ``OUT/.staging-S-<id>.lock``, held while it is
   written, so exports render and write side by side and only the swap below waits for the lock;
2. under OUT's lock, writes a journal ``OUT/.journal-S-<id>.json`` naming the targets, which of them existed, and
   the fingerprint of the ``annotations.json`` it will write;
3. per target, moves the previous file (or folder) to ``OUT/.backup-S-<id>/`` and the staged one into place;
4. replaces ``annotations.json`` atomically (the commit), then removes the journal, the backup and the staging.

:func:`recover` (run at the start of every swap into OUT, holding OUT's lock) finishes what a killed run
left: a journal whose ``annotations.json`` was written is cleaned up (the new export stands); any other is
rolled back from its backup (the previous export stands). Staging and backup folders without a journal are
removed, but for a staging whose claim is still held (an export preparing it now; the kernel drops the ``flock``
of a process that dies). So after any kill, the next run finds the previous or the new export, whole.
``OUT/.export.lock`` (an ``flock`` too) keeps two swaps into OUT from interleaving.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import uuid
from pathlib import Path

from sequences.atomic import write_bytes_atomic, write_text_atomic
from sequences.errors import InputError
from sequences.names import check_name, inside

LOCK = ".export.lock"
ANNOTATIONS = "annotations.json"


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


class OutLock:
    """An exclusive ``flock`` on ``OUT/.export.lock`` (waits for another export into OUT to finish)."""

    def __init__(self, out: Path) -> None:
        self.path = Path(out) / LOCK
        self._fd: int | None = None

    def __enter__(self) -> "OutLock":
        try:
            self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as error:
            raise InputError(self.path.parent, f"cannot write into the export folder ({error.strerror})") from error
        fcntl.flock(self._fd, fcntl.LOCK_EX)
        return self

    def __exit__(self, *exc) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None


def _claim(path: Path):
    """A new file ``path`` already ``flock``-ed by this process (its open file; closing it drops the lock): made
    under a temporary name, locked, then renamed, so that :func:`recover` never finds it unlocked while its owner
    lives. Should recover take the temporary file for a dead process's in between, the rename fails: try again."""
    temporary = path.with_name(path.name + ".tmp")
    while True:
        handle = open(temporary, "xb")
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX)
        try:
            os.rename(temporary, path)
            return handle
        except FileNotFoundError:
            handle.close()


def _claimed(out: Path, tag: str) -> bool:
    """Whether a live process holds the claim of staging ``tag`` (its lock file, or the temporary one being made)."""
    for name in (f".staging-{tag}.lock", f".staging-{tag}.lock.tmp"):
        try:
            fd = os.open(out / name, os.O_RDWR)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        finally:
            os.close(fd)  # drops the lock taken here, if any
    return False


def _tag(name: str) -> str:
    """The ``S-<id>`` of a staging's, backup's or claim's name."""
    return name.split("-", 1)[1].removesuffix(".tmp").removesuffix(".lock")


def recover(out: Path) -> list[str]:
    """Finish or roll back interrupted exports in ``out`` (hold its :class:`OutLock`); returns what was done, a line each."""
    out = Path(out)
    done = []
    current = _sha((out / ANNOTATIONS).read_bytes()) if (out / ANNOTATIONS).is_file() else None
    journals = sorted(out.glob(".journal-*.json"))
    for journal in journals:  # a handful at most: one per killed run
        try:
            record = json.loads(journal.read_text())
            staging, backup = out / record["staging"], out / record["backup"]
            targets, existed, committed = record["targets"], set(record["existed"]), record["annotations_sha"] == current
        except (OSError, ValueError, KeyError, TypeError):
            journal.unlink()
            done.append(f"removed an unreadable journal {journal.name}")
            continue
        if not committed:
            for rel in targets:  # put back what the killed run had moved
                target, old, new = out / rel, backup / rel, staging / rel
                if old.exists() or old.is_symlink():
                    _remove(target)
                    os.replace(old, target)
                elif rel not in existed and not new.exists() and target.exists():
                    _remove(target)  # it was new in the killed run, and had been moved in
        shutil.rmtree(staging, ignore_errors=True)
        shutil.rmtree(backup, ignore_errors=True)
        journal.unlink()
        done.append(f"{'completed' if committed else 'rolled back'} the interrupted export of {record.get('sequence', '?')}")
    live = {p.stem.removeprefix(".journal-") for p in out.glob(".journal-*.json")}
    leftovers = sorted(out.glob(".staging-*")) + sorted(out.glob(".backup-*"))
    for leftover in sorted(leftovers, key=lambda p: p.name.endswith((".lock", ".tmp"))):  # folders before their claims
        tag = _tag(leftover.name)
        if tag in live or _claimed(out, tag):
            continue
        if leftover.is_dir():
            shutil.rmtree(leftover, ignore_errors=True)
            done.append(f"removed {leftover.name}, left by a killed run")
        else:
            leftover.unlink(missing_ok=True)
    return done


class ExportTransaction:
    """Stage one sequence's files (without OUT's lock), then swap them into ``out`` with the new ``annotations.json``
    (holding OUT's lock; see the module notes)."""

    def __init__(self, out: Path, sequence: str) -> None:
        self.out = Path(out)
        self.sequence = check_name(sequence, "sequence name", out)
        self.tag = f"{self.sequence}-{uuid.uuid4().hex[:8]}"
        self.staging = self.out / f".staging-{self.tag}"
        self.backup = self.out / f".backup-{self.tag}"
        self.targets: list[str] = []
        self._claim = None  # the open, flock-ed claim file while this staging is being written

    def _claimed(self) -> None:
        if self._claim is None:
            self.out.mkdir(parents=True, exist_ok=True)
            self._claim = _claim(self.out / f".staging-{self.tag}.lock")

    def _release(self) -> None:
        """Give up the claim (after the staging is swapped in or removed, or on a failure: recover may clean up)."""
        if self._claim is not None:
            (self.out / f".staging-{self.tag}.lock").unlink(missing_ok=True)
            self._claim.close()
            self._claim = None

    def stage(self, rel: str, data: bytes) -> None:
        """A file of the export, ``rel`` to OUT (its folder part made of plain names)."""
        parts = rel.split("/")
        for part in parts:
            check_name(part, "export path part", self.out)
        path = inside(self.staging, *parts)
        self._claimed()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            write_bytes_atomic(path, data)
        except BaseException:
            self._release()  # the caller aborts; a kill here leaves the staging to the next recover
            raise
        top = parts[0] if len(parts) == 1 else "/".join(parts[:2]) if parts[0] in ("masks",) else rel
        if top not in self.targets:
            self.targets.append(top)

    def rename(self, old: str, new: str) -> None:
        """Move a staged file or folder ``old`` to ``new`` (both relative to OUT, plain names): a scene staged under a
        placeholder gets its number, known only under OUT's lock."""
        for part in new.split("/"):
            check_name(part, "export path part", self.out)
        source, target = inside(self.staging, *old.split("/")), inside(self.staging, *new.split("/"))
        target.parent.mkdir(parents=True, exist_ok=True)
        os.rename(source, target)
        self.targets[:] = [new + rel[len(old):] if rel == old or rel.startswith(old + "/") else rel for rel in self.targets]

    def commit(self, annotations: dict) -> None:
        """Swap the staged files in and write ``annotations`` (a whole ``annotations.json``) last; hold OUT's lock."""
        try:
            self._commit(annotations)
        finally:
            self._release()

    def _commit(self, annotations: dict) -> None:
        text = json.dumps(annotations, indent=1)
        for rel in self.targets:
            inside(self.out, *rel.split("/"))
        existed = [rel for rel in self.targets if (self.out / rel).exists()]
        record = {"sequence": self.sequence, "staging": self.staging.name, "backup": self.backup.name, "targets": self.targets,
                  "existed": existed, "annotations_sha": _sha(text.encode("utf-8"))}
        journal = self.out / f".journal-{self.tag}.json"
        write_text_atomic(journal, json.dumps(record))
        for rel in self.targets:  # a few renames
            target = self.out / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            if rel in existed:
                (self.backup / rel).parent.mkdir(parents=True, exist_ok=True)
                os.replace(target, self.backup / rel)
            os.replace(self.staging / rel, target)
        write_text_atomic(self.out / ANNOTATIONS, text)  # the commit point
        journal.unlink()
        shutil.rmtree(self.backup, ignore_errors=True)
        shutil.rmtree(self.staging, ignore_errors=True)

    def abort(self) -> None:
        shutil.rmtree(self.staging, ignore_errors=True)
        self._release()
