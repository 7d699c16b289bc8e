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


#: Documents deeper than this (nested mappings and lists) are refused: no document of ours needs more, and a
#: parser's recursion would end in a traceback first.
MAX_DEPTH = 64


#: The most nodes a YAML document may hold once its aliases are expanded: an anchor bomb's few lines expand to
#: billions, which the first copy of the parsed document (a save) would run out of memory on.
MAX_EXPANDED_NODES = 1_000_000


def _expanded_size(node, sizes: dict) -> int:
    """Nodes of a composed YAML node with every alias expanded (each distinct node counted once per use)."""
    key = id(node)
    if key not in sizes:
        if isinstance(node, yaml.MappingNode):
            sizes[key] = 1 + sum(_expanded_size(k, sizes) + _expanded_size(v, sizes) for k, v in node.value)
        elif isinstance(node, yaml.SequenceNode):
            sizes[key] = 1 + sum(_expanded_size(v, sizes) for v in node.value)
        else:
            sizes[key] = 1
    return sizes[key]


class StrictLoader(yaml.SafeLoader):
    """YAML's safe loader that refuses what no document of ours needs and an attacker would use: duplicate keys (the
    later would silently win), aliases that expand beyond MAX_EXPANDED_NODES nodes (an anchor bomb) and nesting
    deeper than MAX_DEPTH."""

    def compose_document(self):
        node = super().compose_document()
        if node is not None and _expanded_size(node, {}) > MAX_EXPANDED_NODES:
            raise yaml.composer.ComposerError(None, None, f"aliases expand the document beyond {MAX_EXPANDED_NODES:,} nodes", node.start_mark)
        return node

    def compose_node(self, parent, index):
        self._depth = getattr(self, "_depth", 0) + 1
        try:
            if self._depth > MAX_DEPTH:
                raise yaml.composer.ComposerError(None, None, f"nesting deeper than {MAX_DEPTH} levels", self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = set()
            for key_node, _ in node.value:
                if isinstance(key_node, yaml.ScalarNode):
                    if key_node.value in seen:
                        raise yaml.constructor.ConstructorError(None, None, f"duplicate key {key_node.value!r}", key_node.start_mark)
                    seen.add(key_node.value)
        return super().construct_mapping(node, deep=deep)


def _depth_ok(value: Any) -> bool:
    """Whether a parsed JSON value nests at most MAX_DEPTH levels (iteratively: no recursion to overflow)."""
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, (dict, list)):
            if depth > MAX_DEPTH:
                return False
            stack.extend((child, depth + 1) for child in (item.values() if isinstance(item, dict) else item))
    return True


def _refuse_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    keys = [k for k, _ in pairs]
    if len(set(keys)) != len(keys):
        duplicate = next(k for k in keys if keys.count(k) > 1)
        raise ValueError(f"duplicate key {duplicate!r}")
    return dict(pairs)


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
            return yaml.load(text, Loader=loader or StrictLoader)  # noqa: S506 (safe loaders only)
        except yaml.YAMLError as error:
            raise InputError(path, f"malformed YAML: {' '.join(str(error).split())[:300]}") from error
        except RecursionError as error:
            raise InputError(path, f"malformed YAML: nesting deeper than {MAX_DEPTH} levels") from error
    try:
        return parse_json(text)
    except ValueError as error:
        raise InputError(path, f"malformed JSON: {error}") from error


def parse_json(text: str) -> Any:
    """JSON text parsed strictly: ValueError (one line) for malformed text, a duplicate key, or nesting deeper than
    MAX_DEPTH levels."""
    try:
        data = json.loads(text, object_pairs_hook=_refuse_duplicates)
    except json.JSONDecodeError as error:
        raise ValueError(f"{error.msg} (line {error.lineno}, column {error.colno})") from error
    except RecursionError as error:
        raise ValueError(f"nesting deeper than {MAX_DEPTH} levels") from error
    if not _depth_ok(data):
        raise ValueError(f"nesting deeper than {MAX_DEPTH} levels")
    return data


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
