"""The annotation document (``SEQ/annotation.yaml``): load, validate, save atomically.

Poses map object to camera coordinates: p_cam = R p_obj + t, with ``position`` = t (the box
centre in the OpenCV camera frame, metres) and ``orientation`` = R as a quaternion x, y, z, w.
``extents`` are the full box side lengths along object x, y, z (ShapeNet axes, y up), metres.
Unknown keys, at the top level and per frame, are kept on save.

What :func:`save_annotation` writes begins with :data:`FIRST_LINE` and ends with :data:`END_MARKER` (YAML comments):
a file that begins with the first line but lacks the last was cut short (a truncated write or copy) and is refused,
never read as a shorter valid document. Files without the first line (written before, or by hand) load as ever;
an empty one (nothing but blanks and comments) is refused.
"""

from __future__ import annotations

import copy
import hashlib
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .atomic import write_text_atomic
from .documents import StrictLoader, load_document
from .errors import InputError
from .names import check_name, safe_name

CATEGORIES = ("bottle", "bowl", "mug", "can", "camera", "laptop", "other")
SYMMETRIES = ("none", "y")
SOURCES = ("manual", "tracked", "refined")
#: A frame's extra key for the box a person gave an anchor that a tracking run posed on the track (FramePose.placed_matrix).
PLACED_KEY = "placed"
#: Categories whose shapes are rotationally symmetric about object +y by default.
SYMMETRIC_CATEGORIES = ("bottle", "bowl", "can")
DEFAULT_NAME = "annotation.yaml"
#: Box sides (metres) a hand-held object can have, and the least depth (metres) of a box's centre in the camera frame.
EXTENTS_RANGE = (0.001, 2.0)
MIN_BOX_DEPTH = 0.05
#: The first and the last line of every document written here (see the module's docstring).
FIRST_LINE = "# annotation document: whole when its last line is the end marker"
END_MARKER = "# end of annotation document"


def default_symmetry(category: str) -> str:
    return "y" if category in SYMMETRIC_CATEGORIES else "none"


@dataclass
class FramePose:
    """A frame's box pose: position (3,) m in the camera frame, orientation (4,) x y z w (object to camera).

    ``extra`` holds the tracking figures and flags, and under ``placed`` (position, orientation) the box a person gave
    an anchor frame where a tracking run posed it on the track instead (within the placement's tolerance)."""

    position: np.ndarray
    orientation: np.ndarray
    source: str = "manual"
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def matrix(self) -> np.ndarray:
        """4x4 object-to-camera transform."""
        from scipy.spatial.transform import Rotation

        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(self.orientation).as_matrix()
        T[:3, 3] = self.position
        return T

    @property
    def placed_box(self) -> "FramePose":
        """The box a person gave this frame (position and orientation only, a copy, source kept): the one kept under
        ``placed`` where a tracking run posed the frame on the track (engines.anchored_pose), else the pose itself."""
        kept = self.extra.get(PLACED_KEY)
        if kept is None:
            return FramePose(self.position.copy(), self.orientation.copy(), self.source)
        return FramePose(np.asarray(kept["position"], dtype=np.float64), np.asarray(kept["orientation"], dtype=np.float64), self.source)

    @property
    def placed_matrix(self) -> np.ndarray:
        """4x4 object-to-camera matrix of :attr:`placed_box`."""
        return self.placed_box.matrix

    @classmethod
    def from_matrix(cls, T: np.ndarray, source: str = "manual", extra: dict | None = None) -> "FramePose":
        from scipy.spatial.transform import Rotation

        T = np.asarray(T, dtype=np.float64)
        return cls(T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3]).as_quat(), source, dict(extra or {}))


@dataclass
class Annotation:
    """The whole annotation document of one sequence."""

    sequence: str
    category: str = "other"
    symmetry: str = "none"
    extents: np.ndarray = field(default_factory=lambda: np.array([0.1, 0.1, 0.1]))
    frames: dict[str, FramePose] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)

    def copy(self) -> "Annotation":
        return copy.deepcopy(self)

    def frames_with_source(self, *sources: str) -> list[str]:
        return [k for k, f in self.frames.items() if f.source in sources]

    def to_dict(self) -> dict:
        out: dict[str, Any] = {
            "sequence": self.sequence,
            "category": self.category,
            "symmetry": self.symmetry,
            "extents": [float(x) for x in self.extents],
        }
        out.update({k: v for k, v in self.extra.items() if k not in out and k != "frames"})
        frames = {}
        for frame_id in sorted(self.frames):
            f = self.frames[frame_id]
            entry: dict[str, Any] = {
                "position": [float(x) for x in f.position],
                "orientation": [float(x) for x in f.orientation],
                "source": f.source,
            }
            entry.update({k: _plain(v) for k, v in f.extra.items() if k not in entry})
            frames[str(frame_id)] = entry
        out["frames"] = frames
        return out


def _plain(value: Any) -> Any:
    """numpy scalars and arrays to plain YAML-safe Python."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _vector(path: Path, where: str, value: Any, n: int) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise InputError(path, f"{where} must be a list of {n} numbers, got {value!r}")
    if any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in value):
        raise InputError(path, f"{where} must be a list of {n} numbers, got {value!r}")
    array = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(array)):
        raise InputError(path, f"{where} has a NaN or infinite value: {value!r}")
    return array


def _box(path: Path, where: str, entry: dict) -> tuple[np.ndarray, np.ndarray]:
    """The ``position`` (3,) and ``orientation`` (4,, x y z w, made unit) of a box's mapping ``entry``; InputError
    naming ``where`` for a wrong length, a non-number, a NaN, or a quaternion whose norm is not 1."""
    position = _vector(path, f"{where} position", entry.get("position"), 3)
    orientation = _vector(path, f"{where} orientation", entry.get("orientation"), 4)
    norm = float(np.linalg.norm(orientation))
    if not math.isclose(norm, 1.0, abs_tol=1e-3):
        raise InputError(path, f"{where} orientation is not a unit quaternion (norm {norm:.4g}; order x, y, z, w)")
    return position, orientation / norm


def annotation_from_dict(data: Any, path: str | Path = "<document>", default_sequence: str = "") -> Annotation:
    """Validate a parsed document; raises InputError naming ``path`` and the problem."""
    path = Path(path)
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise InputError(path, "annotation document must be a mapping (sequence, category, symmetry, extents, frames)")
    # the name becomes file names (OUT/<sequence>.obj): a document's own must be a plain name; a folder's is made one
    named = data.get("sequence")
    if named in (None, ""):
        sequence = safe_name(str(default_sequence)) if default_sequence else ""
    elif not isinstance(named, str):  # YAML reads an unquoted 00015 as a number (13: octal)
        raise InputError(path, f"sequence name must be text, got the number {named!r}: quote it ('00015')")
    else:
        sequence = check_name(named, "sequence name", path)
    category = data.get("category", "other")
    if category not in CATEGORIES:
        raise InputError(path, f"category {category!r} is not one of {', '.join(CATEGORIES)}")
    symmetry = data.get("symmetry", default_symmetry(category))
    if symmetry is None or symmetry is False:
        symmetry = "none"
    if symmetry not in SYMMETRIES:
        raise InputError(path, f"symmetry {symmetry!r} is not one of {', '.join(SYMMETRIES)}")
    extents = _vector(path, "extents", data.get("extents", [0.1, 0.1, 0.1]), 3)
    if np.any(extents <= 0):
        raise InputError(path, f"extents must be positive (an empty box), got {extents.tolist()}")
    if np.any(extents < EXTENTS_RANGE[0]) or np.any(extents > EXTENTS_RANGE[1]):
        raise InputError(path, f"extents {extents.tolist()} m are outside {EXTENTS_RANGE[0]}-{EXTENTS_RANGE[1]} m (a hand-held object, in metres)")
    frames_data = data.get("frames") or {}
    if not isinstance(frames_data, dict):
        raise InputError(path, "frames must be a mapping from frame id to pose")
    frames: dict[str, FramePose] = {}
    for key, entry in frames_data.items():
        frame_id = check_name(str(key), "frame id", path)
        where = f"frame {frame_id}"
        if not isinstance(entry, dict):
            raise InputError(path, f"{where} must be a mapping with position and orientation")
        position, orientation = _box(path, where, entry)
        if position[2] <= MIN_BOX_DEPTH:
            raise InputError(path, f"{where} box centre is at z = {position[2]:g} m: not in front of the camera (z must exceed {MIN_BOX_DEPTH} m)")
        source = entry.get("source", "manual")
        if source not in SOURCES:
            raise InputError(path, f"{where} source {source!r} is not one of {', '.join(SOURCES)}")
        extra = {k: v for k, v in entry.items() if k not in ("position", "orientation", "source")}
        if PLACED_KEY in extra:
            kept = extra[PLACED_KEY]
            if not isinstance(kept, dict):
                raise InputError(path, f"{where} {PLACED_KEY} must be a mapping with position and orientation (the box a person placed)")
            placed_position, placed_orientation = _box(path, f"{where} {PLACED_KEY}", kept)
            extra[PLACED_KEY] = {"position": placed_position.tolist(), "orientation": placed_orientation.tolist()}
        frames[frame_id] = FramePose(position, orientation, source, extra)
    extra = {k: v for k, v in data.items() if k not in ("sequence", "category", "symmetry", "extents", "frames")}
    return Annotation(sequence, category, symmetry, extents, frames, extra)


class _KeysAsTextLoader(StrictLoader):
    """SafeLoader that keeps scalar mapping keys as their literal text.

    YAML 1.1 reads an unquoted frame id such as ``0000012`` as the octal integer 10; frame ids
    are text, so keys are never converted.
    """

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            for key_node, _ in node.value:
                if isinstance(key_node, yaml.ScalarNode):
                    key_node.tag = "tag:yaml.org,2002:str"
        return super().construct_mapping(node, deep=deep)


def load_annotation(path: str | Path, default_sequence: str | None = None) -> Annotation:
    """Read and validate an annotation document."""
    path = Path(path)
    if default_sequence is None:
        default_sequence = path.resolve().parent.name
    # a SafeLoader that reads every key as text (frame ids like 0000012 stay strings); parsed as YAML
    # whatever the file's suffix, since --annotation may name any file
    data = load_document(path, "annotation document", loader=_KeysAsTextLoader, as_yaml=True)
    check_whole(path, data)
    return annotation_from_dict(data, path, default_sequence)


def check_whole(path: Path, data: Any) -> None:
    """InputError naming ``path`` when the document is empty (``data``, its parsed content, is None) or was cut short
    (it begins with :data:`FIRST_LINE` but does not end with :data:`END_MARKER`)."""
    earlier = "its .bak or .orig beside it may hold the last whole version"
    if data is None:
        raise InputError(path, f"the annotation document is empty (an emptied or truncated file); {earlier}")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(path, f"cannot read annotation document ({error.__class__.__name__})") from error
    lines = [line.rstrip() for line in text.splitlines() if line.strip()]
    if lines and lines[0] == FIRST_LINE and lines[-1] != END_MARKER:
        raise InputError(path, f"the annotation document was cut short: its last line is not {END_MARKER!r} (a truncated write "
                               f"or copy; if you edited it, end it with that line again); {earlier}")


def document_text(annotation: Annotation) -> str:
    """The document as the YAML text ``save_annotation`` writes, between :data:`FIRST_LINE` and :data:`END_MARKER`."""
    body = yaml.safe_dump(annotation.to_dict(), sort_keys=False, default_flow_style=None, width=120)
    return f"{FIRST_LINE}\n{body}{END_MARKER}\n"


def save_annotation(annotation: Annotation, path: str | Path, backup: bool = True) -> Path:
    """Write the document atomically (temporary file, fsync, rename); keep the previous one as ``.bak``."""
    return write_text_atomic(path, document_text(annotation), backup=backup)


def save_checked(annotation: Annotation, path: str | Path, expected: str | None, backup: bool = True) -> str:
    """Save the document unless the file on disk changed since it was read (its fingerprint then was ``expected``,
    None: it did not exist); return the new file's fingerprint.

    A change another program made is never overwritten: this version goes beside it, to
    ``<name>.refused-<time>.yaml``, and InputError names both.
    """
    from .lock import check_unchanged

    path = Path(path)
    text = document_text(annotation)
    try:
        check_unchanged(path, expected)
    except InputError as error:
        kept = path.with_name(f"{path.stem}.refused-{time.strftime('%Y%m%d-%H%M%S')}{path.suffix or '.yaml'}")
        write_text_atomic(kept, text)
        raise InputError(path, f"{error.problem}; this session's version is in {kept.name}") from None
    write_text_atomic(path, text, backup=backup)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def load_checked(path: str | Path, default_sequence: str | None = None) -> tuple[Annotation, str]:
    """The document and the fingerprint of the bytes it was read from (for :func:`save_checked`)."""
    from .lock import fingerprint

    before = fingerprint(path)
    annotation = load_annotation(path, default_sequence)
    if fingerprint(path) != before:
        raise InputError(path, "changed while it was being read; try again")
    return annotation, before


def annotation_path(sequence_root: str | Path, override: str | Path | None = None) -> Path:
    """The document path: ``--annotation FILE`` if given, else ``SEQ/annotation.yaml``."""
    return Path(override) if override else Path(sequence_root) / DEFAULT_NAME
