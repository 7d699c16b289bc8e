"""Reading a JSON or YAML document from disk, with every way it can fail as a one-line InputError.

The commands read several kinds of document (camera.yaml, the annotation document, the evaluate
config, a REDWOOD75 annotations.json); each reports a missing, unreadable or malformed file the
same way: the path and the problem, on one line.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterable

import yaml

from .errors import InputError


def load_document(path: str | Path, what: str, *, as_yaml: bool | None = None, loader: type | None = None,
                  missing: str | None = None) -> Any:
    """The parsed content of ``path``: YAML if ``as_yaml`` (by default: for ``.yaml``/``.yml`` files), else JSON.

    ``what`` names the document in messages ("config", "camera file"); ``missing`` replaces the
    message for a file that does not exist; ``loader`` is a yaml Loader class (SafeLoader by
    default).  Raises InputError naming ``path`` when the file is missing, unreadable or malformed.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError as error:
        raise InputError(path, missing or f"{what} not found") from error
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(path, f"cannot read {what} ({error.__class__.__name__})") from error
    if as_yaml if as_yaml is not None else path.suffix.lower() in (".yaml", ".yml"):
        try:
            return yaml.load(text, Loader=loader or yaml.SafeLoader)  # noqa: S506 (safe loaders only)
        except yaml.YAMLError as error:
            raise InputError(path, f"malformed YAML: {' '.join(str(error).split())}") from error
    try:
        return json.loads(text)
    except json.JSONDecodeError as error:
        raise InputError(path, f"malformed JSON: {error}") from error


def load_mapping(path: str | Path, what: str, keys: Iterable[str], *, as_yaml: bool | None = None) -> dict:
    """``path``'s document as a dict whose keys all lie in ``keys`` (an empty file is an empty dict).

    ``what`` is the short name used in messages ("config", "camera"): "<what> must be a mapping",
    "unknown <what> keys [...]; expected [...]".
    """
    path = Path(path)
    data = load_document(path, f"{what} file", as_yaml=as_yaml)
    if data is None:
        return {}
    keys = list(keys)
    if not isinstance(data, dict):
        raise InputError(path, f"{what} must be a mapping of {', '.join(keys)}")
    unknown = sorted(set(map(str, data)) - set(keys))
    if unknown:
        raise InputError(path, f"unknown {what} keys {unknown}; expected {keys}")
    return data
