"""Names are data, never paths: sequence and frame names checked against one character set, and paths built
from them confined to the folder they are written under.

A document, a predictions file or a dataset names sequences and frames; the tools build file names from
them (``OUT/<sequence>.obj``, ``OUT/masks/<sequence>/<frame>.png``). A name such as ``../../thesis`` or
``/home/me`` would write anywhere, so every name is checked where it is read (:func:`check_name`), and every
path written is built by :func:`inside`, which refuses one that leaves its folder.
"""

from __future__ import annotations

import re
from pathlib import Path

from .errors import InputError

#: Letters, digits, '.', '_', '-' and '+'; starting with a letter or digit; at most 128 characters.
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]{0,127}")
_UNSAFE = re.compile(r"[^A-Za-z0-9._+-]")


def is_name(value: object) -> bool:
    """Whether ``value`` is a string of :data:`NAME`'s characters (no separator, no '..', not hidden)."""
    return isinstance(value, str) and NAME.fullmatch(value) is not None and ".." not in value


def check_name(value: object, what: str, source: str | Path | None) -> str:
    """``value`` if it is a safe name, else InputError naming ``source`` and the problem."""
    if not is_name(value):
        shown = repr(value) if len(repr(value)) <= 60 else repr(value)[:57] + "..."
        raise InputError(source, f"{what} {shown} is not a plain name (letters, digits, '.', '_', '-', '+'; "
                                 "no path separators, no '..', at most 128 characters)")
    return value


def safe_name(text: str, fallback: str = "sequence") -> str:
    """A safe name made from ``text`` (a folder's name): unsafe characters become '_', a leading one is dropped."""
    name = _UNSAFE.sub("_", text).strip("._-+").replace("..", "_")[:128]
    return name if is_name(name) else fallback


def inside(root: str | Path, *parts: str) -> Path:
    """``root/parts...``, refused (InputError) unless it lies inside ``root`` once both are resolved (symbolic links
    and '..' followed): the one way the tools build a path they write from a name."""
    root = Path(root)
    path = root.joinpath(*parts)
    base = root.resolve()
    resolved = path.resolve()
    if resolved != base and base not in resolved.parents:
        raise InputError(path, f"would be written outside {root} (refused)")
    return path
