"""What the exports share: the index of the sequences an export folder holds, and the staged swap.

Every export into ``OUT`` is one :class:`reconstruct.transaction.ExportTransaction`, whose commit point is
``OUT/annotations.json``. For REDWOOD75 that file is the format's own; for BOP and NOCS, whose formats name
scenes and images by numbers, it is our index of the sequences in ``OUT``: ``{sequence: {"format": "bop" |
"nocs", ...where its files are, which frame each image is}}``. BOP's and NOCS's tools never read it; our
readers use it to give back the sequence names and frame ids (``evaluate.datasets``). One folder holds one
format: :func:`folder_format` tells which, and an export of another format into it is refused.

:func:`export_unit` runs one sequence's export in two steps. First, without ``OUT``'s lock, the format's
``prepare`` renders and stages every file that does not depend on what ``OUT`` holds (streamed, one frame at a
time, so memory stays flat), its scene folder under the placeholder name :data:`PENDING`. Then, under the lock:
recover a killed export, read the index, and let ``finish`` number the scene (the sequence's number if it has
one, else the number the caller reserved for it, else the least free one), rename the placeholder, stage the few
small files that hold the number or are shared by every scene, and swap them in with the new index last. So
exports into one folder render side by side and wait for each other only for their renames. A folder (a BOP or
NOCS scene) is swapped as one unit: a re-export with fewer frames leaves no image of the old one behind.

A batch reserves the numbers before its units start (:func:`reserve_numbers`, in the command line's order), so
that the scenes are numbered alike whichever unit finishes first.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from sequences.documents import parse_json
from sequences.errors import InputError
from sequences.names import check_name, inside, is_name

from .transaction import ANNOTATIONS, ExportTransaction, OutLock, recover

#: The formats ``reconstruct-sequence --format`` writes; the first is the default.
FORMATS = ("redwood75", "bop", "nocs")

#: stage(rel, data): write one file of the export, ``rel`` to OUT ('/'-separated plain names).
Stage = Callable[[str, bytes], None]
#: prepare(stage) -> what finish needs: the heavy part, without OUT's lock.
Prepare = Callable[[Stage], Any]
#: finish(index, transaction, prepared) -> (index entry, folders to swap as units, files to remove after the commit).
Finish = Callable[[dict, ExportTransaction, Any], tuple[dict, list[str], list[str]]]
#: The scene folder's name in the staging until its number is known (a number is never this).
PENDING = "pending"


def read_index(out: Path) -> dict:
    """``OUT/annotations.json`` (empty when absent); InputError when it is not a JSON mapping."""
    path = Path(out) / ANNOTATIONS
    if not path.exists():
        return {}
    try:
        data = parse_json(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise InputError(path, f"existing index is unreadable ({' '.join(str(error).split())}); not overwriting it") from error
    if not isinstance(data, dict):
        raise InputError(path, "existing annotations.json is not a mapping of sequences; not overwriting it")
    return data


def folder_format(out: Path) -> str | None:
    """The format of the export already in ``out``: ``"bop"`` or ``"nocs"`` (every index entry says so),
    ``"redwood75"`` (entries without a format), None for an empty or absent folder."""
    out = Path(out)
    index = read_index(out) if out.is_dir() else {}
    formats = {entry.get("format", "redwood75") if isinstance(entry, dict) else "redwood75" for entry in index.values()}
    if len(formats) > 1:
        raise InputError(out / ANNOTATIONS, f"holds entries of several formats ({', '.join(sorted(formats))}); not writing into it")
    if formats:
        return formats.pop()
    if (out / "models" / "models_info.json").is_file():
        return "bop"
    if (out / "gts").is_dir():
        return "nocs"
    return None


def check_folder_format(out: Path, fmt: str) -> None:
    """InputError unless ``out`` is empty, absent, or already holds ``fmt`` exports (formats are never mixed)."""
    found = folder_format(out)
    if found is not None and found != fmt:
        raise InputError(out, f"holds a {found} export; a {fmt} export here would mix two formats in one folder (choose another output folder)")


def next_number(index: dict, key: str, taken: set[int]) -> int:
    """The least number from 1 not used by ``index``'s entries under ``key`` nor in ``taken`` (scenes on disk)."""
    used = {entry.get(key) for entry in index.values() if isinstance(entry, dict)} | set(taken)
    number = 1
    while number in used:
        number += 1
    return number


def scene_number(index: dict, name: str, key: str, taken: set[int], reserved: int | None = None) -> int:
    """The number of sequence ``name``'s scene: its entry's, else ``reserved`` where no other entry nor ``taken``
    (scenes on disk) uses it, else the least free one."""
    previous = index.get(name)
    if isinstance(previous, dict) and isinstance(previous.get(key), int) and not isinstance(previous.get(key), bool):
        return previous[key]
    used = {entry.get(key) for other, entry in index.items() if other != name and isinstance(entry, dict)} | set(taken)
    if isinstance(reserved, int) and reserved >= 1 and reserved not in used:
        return reserved
    return next_number(index, key, taken)


def reserve_numbers(index: dict, names: list[str], key: str, taken: set[int]) -> dict[str, int]:
    """The scene numbers that exports of ``names`` one after another, in this order, would give (each its entry's
    number, else the least free one): what a batch hands its units, whichever of them finishes first."""
    index = {k: v for k, v in index.items()}
    numbers = {}
    for name in names:
        numbers[name] = scene_number(index, name, key, taken)
        index[name] = {**(index[name] if isinstance(index.get(name), dict) else {}), key: numbers[name]}
    return numbers


def export_unit(out: str | Path, sequence: str, fmt: str, prepare: Prepare, finish: Finish) -> Path:
    """Export one sequence into ``out`` as one staged unit (see the module notes); returns the index's path."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "output path exists and is not a folder")
    name = check_name(sequence, "sequence name", out)
    if out.is_dir():  # refuse a broken index or another format before any work (checked again under the lock)
        check_folder_format(out, fmt)
    out.mkdir(parents=True, exist_ok=True)
    transaction = ExportTransaction(out, name)
    try:
        prepared = prepare(transaction.stage)
    except BaseException:
        transaction.abort()
        raise
    with OutLock(out):
        try:
            recover(out)
            check_folder_format(out, fmt)
            index = read_index(out)
            entry, units, obsolete = finish(dict(index), transaction, prepared)
            # one swap target per unit folder, not one per file inside it
            grouped: list[str] = []
            for rel in transaction.targets:
                unit = next((u for u in units if rel == u or rel.startswith(u + "/")), rel)
                if unit not in grouped:
                    grouped.append(unit)
            transaction.targets[:] = grouped
            # REDWOOD75's index is the format's own file, whose entries name no format
            index[name] = entry if fmt == FORMATS[0] else {"format": fmt, **entry}
            transaction.commit(index)
        except BaseException:
            transaction.abort()
            recover(out)  # a failed swap is rolled back now, not at the next run
            raise
        for rel in obsolete:  # the previous export's files the new one does not replace (unreferenced now)
            parts = rel.split("/")
            if all(is_name(part) for part in parts):  # names read from the index: plain names only, inside OUT
                path = inside(out, *parts)
                if path.is_file():
                    path.unlink()
    return out / ANNOTATIONS
