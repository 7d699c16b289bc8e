"""The annotation session shared by every browser tab: document, current frame, undo/redo, autosave.

One ``AppState`` lives in the server; all clients read and change it, so every tab sees the same
document and frame. Every change goes through :meth:`AppState.edit` (or undo/redo), which keeps
the previous document on the undo stack, saves the document atomically (the document as the session
found it kept as ``.orig`` at the first save, the previous file as ``.bak``) and tells the listeners
(the scene and the panels) to redraw.

The session holds the document's lock (:mod:`sequences.lock`) while it lives: a second server, or an
``annotate --track`` run, on the same document finds it taken. A session that finds it taken opens the
document read-only and says so; a save never overwrites a change another program made to the file.

Poses are object to camera (p_cam = R p_obj + t), metres, quaternions x, y, z, w.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Callable

import numpy as np

from sequences.annotation import (
    Annotation,
    FramePose,
    annotation_path,
    default_symmetry,
    load_checked,
    save_checked,
)
from sequences.atomic import write_bytes_atomic
from sequences.errors import InputError
from sequences.lock import DocumentLock
from sequences.reader import Sequence
from sequences.typical_extents import typical_extents

from .app_review import Flagged, is_flagged, mark_fixed, next_in_review, review_list, review_thresholds

#: Box side length (m) of a new document's first box when its category is ``other`` (sequences.typical_extents).
DEFAULT_BOX_SIZE = float(typical_extents("other")[0])
#: Half width (px) of the centre window whose median depth places a new document's first box.
CENTRE_WINDOW = 20
UNDO_DEPTH = 200
#: Default box orientation: object +y up (camera -y), object -z (front, mug handle: REDWOOD75/NOCS convention)
#: towards the camera, i.e. object +z along camera +z.
FACING_CAMERA = np.array([0.0, 0.0, 1.0, 0.0])  # 180 degrees about z: x y z w

STATUSES = ("manual", "tracked", "refined", "flagged", "none")

Listener = Callable[[str], None]


def frame_status(annotation: Annotation, frame_id: str) -> str:
    """One of :data:`STATUSES` for a frame of the document."""
    pose = annotation.frames.get(frame_id)
    if pose is None:
        return "none"
    if is_flagged(pose):
        return "flagged"
    return pose.source


def default_position(sequence: Sequence, frame: int = 0, window: int = CENTRE_WINDOW) -> np.ndarray:
    """Camera-frame point (m) on the optical axis at the median valid depth of the centre pixels.

    Falls back to the median of the whole frame's valid depth when the centre has none.
    """
    depth = sequence.depth(frame)
    cam = sequence.camera
    # pixels whose centres lie within ``window`` px of the principal point, on both axes
    v_lo, v_hi = max(int(np.ceil(cam.cy - window)), 0), int(np.floor(cam.cy + window)) + 1
    u_lo, u_hi = max(int(np.ceil(cam.cx - window)), 0), int(np.floor(cam.cx + window)) + 1
    centre = depth[v_lo:v_hi, u_lo:u_hi]
    valid = centre[centre > 0]
    if valid.size == 0:
        valid = depth[depth > 0]
    z = float(np.median(valid))
    return np.array([0.0, 0.0, z])


#: The category a new document starts with, until the annotator chooses one.
NEW_DOCUMENT_CATEGORY = "other"


def new_document(sequence: Sequence, category: str = NEW_DOCUMENT_CATEGORY) -> Annotation:
    """A fresh document: named after the folder, the category's typical box (sequences.typical_extents)."""
    annotation = Annotation(
        sequence=sequence.name,
        category=category,
        symmetry=default_symmetry(category),
        extents=typical_extents(category),
    )
    return annotation


def change_category(doc: Annotation, category: str) -> None:
    """Set the document's category and its default symmetry; the extents become the new category's typical ones
    while they are still the old category's (nobody sized the box yet): a default, never a code path."""
    untouched = np.allclose(doc.extents, typical_extents(doc.category), atol=1e-6)
    doc.category = category
    doc.symmetry = default_symmetry(category)
    if untouched:
        doc.extents = typical_extents(category)


class AppState:
    """The shared session: the sequence, its document, the current frame and the edit history."""

    def __init__(self, sequence: Sequence, document: str | Path | None = None, category: str = NEW_DOCUMENT_CATEGORY) -> None:
        self.sequence = sequence
        self.path = annotation_path(sequence.root, document)
        self.lock = threading.RLock()
        if not self.path.parent.exists():
            raise InputError(self.path, "folder of the annotation document does not exist")
        self.document_lock = DocumentLock(self.path, "annotate (browser)")
        #: why this session cannot write the document (None: it can): the lock is another's, or the folder is read-only
        self.read_only: str | None = None
        try:
            self.document_lock.acquire()
        except InputError as error:
            self.read_only = f"Read-only: {error}"
        self._original: bytes | None = None  # the document as the session found it (.orig at the first save)
        if self.path.exists():
            self.annotation, self._fingerprint = load_checked(self.path, default_sequence=sequence.name)
            self._original = self.path.read_bytes()
            unknown = sorted(set(self.annotation.frames) - set(sequence.ids))
            if unknown:
                self.document_lock.release()
                raise InputError(self.path, f"frames {unknown[:3]} are not in the sequence {sequence.root}")
            self.is_new = False
        else:
            self.annotation = new_document(sequence, category)
            self._fingerprint = None
            self.is_new = True  # nothing on disk until the first change
        self._default_position = default_position(sequence, 0)
        self._thresholds = review_thresholds()
        self.frame = 0
        self.undo_stack: list[Annotation] = []
        self.redo_stack: list[Annotation] = []
        self.saves = 0
        #: where the current box rests on a clicked surface: (frame id, the clicked point, the box centre placed there;
        #: camera frame, m); turns keep such a box on that surface until it is moved (app_placing, app_moving)
        self.contact: tuple[str, np.ndarray, np.ndarray] | None = None
        self._listeners: list[Listener] = []
        #: called with a one-line message when a change cannot be saved (the page shows it)
        self.on_error: Callable[[str], None] | None = None

    # --- observers -------------------------------------------------------------------------
    def subscribe(self, listener: Listener) -> None:
        """Call ``listener(kind)`` after every change; kind is "frame" or "document"."""
        self._listeners.append(listener)

    def _notify(self, kind: str) -> None:
        for listener in list(self._listeners):
            listener(kind)

    # --- frames ----------------------------------------------------------------------------
    @property
    def frame_id(self) -> str:
        return self.sequence.frames[self.frame].id

    def set_frame(self, index: int) -> None:
        """Go to frame ``index`` (clamped to the sequence)."""
        index = int(np.clip(index, 0, len(self.sequence) - 1))
        with self.lock:
            if index == self.frame:
                return
            self.frame = index
        self._notify("frame")

    def step(self, delta: int) -> None:
        self.set_frame(self.frame + delta)

    def status(self, frame_id: str | None = None) -> str:
        with self.lock:
            return frame_status(self.annotation, frame_id or self.frame_id)

    def statuses(self) -> list[str]:
        """Status of every frame, in sequence order."""
        with self.lock:
            return [frame_status(self.annotation, f.id) for f in self.sequence.frames]

    def review(self) -> list[Flagged]:
        """The flagged frames, worst first (app_review)."""
        with self.lock:
            return review_list(self.annotation, self.sequence.ids, self._thresholds)

    def next_flagged(self) -> int | None:
        """Index of the frame after the current one in the review list (worst first, wrapping; its first when the
        current frame is not in it), or None when no frame is flagged."""
        with self.lock:
            return next_in_review([item.index for item in self.review()], self.frame)

    # --- poses -----------------------------------------------------------------------------
    def pose(self, frame_id: str | None = None) -> tuple[FramePose, bool]:
        """The box pose shown in a frame and whether the frame has its own.

        A frame without a pose shows the pose of the nearest frame that has one, or the default
        box (the document's extents, at the centre depth of the first frame, upright facing the camera).
        """
        with self.lock:
            frame_id = frame_id or self.frame_id
            own = self.annotation.frames.get(frame_id)
            if own is not None:
                return own, True
            if self.annotation.frames:
                here = self.sequence.index(frame_id)
                known = [self.sequence.index(k) for k in self.annotation.frames]
                nearest = self.sequence.frames[min(known, key=lambda i: (abs(i - here), i))].id
                src = self.annotation.frames[nearest]
                return FramePose(src.position.copy(), src.orientation.copy(), "manual"), False
            return FramePose(self._default_position.copy(), FACING_CAMERA.copy(), "manual"), False

    def box(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
        """The box shown in the current frame: copies of its position (3,) m, orientation (4,) x y z w and the
        document's extents (3,) m, and whether the frame has its own pose (see :meth:`pose`)."""
        with self.lock:
            pose, own = self.pose()
            return pose.position.copy(), pose.orientation.copy(), self.annotation.extents.copy(), own

    def set_contact(self, frame_id: str, point, position) -> None:
        """Remember that the box of ``frame_id`` at ``position`` rests on the clicked surface ``point`` (m)."""
        with self.lock:
            self.contact = (frame_id, np.asarray(point, dtype=np.float64).copy(), np.asarray(position, dtype=np.float64).copy())

    def contact_point(self) -> np.ndarray | None:
        """The clicked point the current frame's box rests on, or None once it moved (or another frame is shown)."""
        with self.lock:
            if self.contact is None:
                return None
            frame_id, point, position = self.contact
            pose = self.annotation.frames.get(self.frame_id)
            if frame_id != self.frame_id or pose is None or not np.allclose(pose.position, position, atol=1e-9):
                return None
            return point.copy()

    def document(self) -> Annotation:
        """A copy of the document, read under the lock: what a panel works on while another tab may edit."""
        with self.lock:
            return self.annotation.copy()

    def has_pose(self, frame_id: str | None = None) -> bool:
        """Whether ``frame_id`` (default: the current frame) has a box, read under the lock."""
        with self.lock:
            return (self.frame_id if frame_id is None else frame_id) in self.annotation.frames

    # --- changes ---------------------------------------------------------------------------
    def edit(self, change: Callable[[Annotation], None]) -> None:
        """Apply ``change`` to the document as one undoable step, save it, redraw."""
        with self.lock:
            before = self.annotation.copy()
            try:
                change(self.annotation)
                self._save()
            except BaseException as error:
                # the file on disk is still the previous version (atomic write): so is the session
                self.annotation = before
                self._report(error)
                raise
            self.undo_stack.append(before)
            del self.undo_stack[:-UNDO_DEPTH]
            self.redo_stack.clear()
        self._notify("document")

    def set_pose(self, position, orientation, source: str = "manual", frame_id: str | None = None, keep_extra: bool = False) -> None:
        """Give a frame (default: the current one) a pose; a manual edit drops tracking figures and flags."""
        position = np.asarray(position, dtype=np.float64)
        orientation = np.asarray(orientation, dtype=np.float64)
        if not (np.all(np.isfinite(position)) and np.all(np.isfinite(orientation))):
            raise ValueError("pose has a NaN or infinite value")
        orientation = orientation / np.linalg.norm(orientation)
        frame_id = frame_id or self.frame_id

        def change(doc: Annotation) -> None:
            old = doc.frames.get(frame_id)
            extra = dict(old.extra) if (old is not None and keep_extra) else mark_fixed(old, {})
            doc.frames[frame_id] = FramePose(position.copy(), orientation.copy(), source, extra)

        self.edit(change)

    def set_category(self, category: str) -> None:
        """Change the category (see :func:`change_category`), as one undoable change."""
        self.edit(lambda doc: change_category(doc, category))

    def set_extents(self, extents) -> None:
        extents = np.asarray(extents, dtype=np.float64)
        if extents.shape != (3,) or not np.all(np.isfinite(extents)) or np.any(extents <= 0):
            raise ValueError(f"extents must be three positive numbers, got {extents}")

        def change(doc: Annotation) -> None:
            doc.extents = extents.copy()

        self.edit(change)

    def set_extent(self, axis: int, value: float) -> None:
        """Set one side of the box (metres) as one undoable change; the other sides stay as they are in the document
        then (another tab may have changed them)."""
        if axis not in (0, 1, 2) or not (np.isfinite(value) and value > 0):
            raise ValueError(f"extent {axis} must be a positive number, got {value}")

        def change(doc: Annotation) -> None:
            doc.extents = doc.extents.copy()
            doc.extents[axis] = float(value)

        self.edit(change)

    def _restore(self, source: list[Annotation], target: list[Annotation]) -> bool:
        with self.lock:
            if not source:
                return False
            current = self.annotation
            self.annotation = source[-1]
            try:
                self._save()
            except BaseException as error:
                self.annotation = current
                self._report(error)
                raise
            source.pop()
            target.append(current)
        self._notify("document")
        return True

    def undo(self) -> bool:
        """Go back one change; False when there is none."""
        return self._restore(self.undo_stack, self.redo_stack)

    def redo(self) -> bool:
        """Redo the last undone change; False when there is none."""
        return self._restore(self.redo_stack, self.undo_stack)

    def _report(self, error: BaseException) -> None:
        if self.on_error is not None:
            self.on_error(f"Not saved ({error}); {self.path} is unchanged.")

    def _save(self) -> None:
        if self.read_only:
            raise InputError(self.path, self.read_only.removeprefix("Read-only: "))
        if self.saves == 0 and self._original is not None:
            write_bytes_atomic(self.path.with_name(self.path.name + ".orig"), self._original)
        self._fingerprint = save_checked(self.annotation, self.path, self._fingerprint)
        self.saves += 1
        self.is_new = False

    def close(self) -> None:
        """End the session: give the document's lock up."""
        self.document_lock.release()
