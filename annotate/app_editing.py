"""The box panel: gizmo and face drags, extents, fit, snap upright, category, undo/redo.

Steps along and about the axes are the move panel's (app_moving), placing by pointing the placing panel's
(app_placing). Each action is one undoable change of the shared document (saved at once). Hotkeys are viser
commands (also in its command palette, cmd/ctrl+K).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from evaluate.geometry import quat_to_matrix
from sequences.annotation import CATEGORIES, SYMMETRIES
from sequences.pointcloud import frame_points

from . import box_edits
from .app_scene import FACES, xyzw

if TYPE_CHECKING:
    from .app import App

#: Snap upright trusts an estimated symmetry axis only this close to the box's y (degrees).
MAX_AXIS_SNAP_DEG = 20.0


class EditingPanel:
    """GUI for changing the box of the current frame and the document's category, symmetry and extents."""

    def __init__(self, app: "App") -> None:
        self.app = app
        gui = app.server.gui
        document = app.state.document()
        with gui.add_folder("Box"):
            self.category = gui.add_dropdown("Category", CATEGORIES, initial_value=document.category,
                                             hint="the object's category: sets the typical box size until you size it; bottle, bowl and can also set symmetry y")
            self.symmetry = gui.add_dropdown("Symmetry", SYMMETRIES, initial_value=document.symmetry, hint="y: rotationally symmetric about object +y")
            e = document.extents * 1000
            self.extent_inputs = [
                gui.add_number(f"{name} (mm)", initial_value=float(round(v, 1)), min=1.0, max=5000.0, step=0.5, hint=f"the box's full side along object {a}, mm")
                for name, a, v in zip(("Width x", "Height y", "Depth z"), ("x", "y (up)", "z (front: -z)"), e)
            ]
            self.place = gui.add_button("Place box in this frame")
            self.fit = gui.add_button(app.key_label("Fit box to points", "G"))
            self.upright = gui.add_button(app.key_label("Snap upright", "U"))
            self.delete = gui.add_button("Remove pose of this frame")
            self.undo = gui.add_button(app.key_label("Undo", "Z", "cmd/ctrl"))
            self.redo = gui.add_button(app.key_label("Redo", "Y", "cmd/ctrl"))
            self.face_box = gui.add_checkbox("Face handles", initial_value=True, hint="shown: drag a face's arrow to move that face alone")

        state = app.state
        self.category.on_update(self._on_category)
        self.symmetry.on_update(self._on_symmetry)
        for axis, number in enumerate(self.extent_inputs):
            number.on_update(lambda event, axis=axis: self._on_extent(axis, event.target.value))
        self.place.on_click(lambda _: self.place_here())
        self.fit.on_click(lambda _: self.fit_to_points())
        self.upright.on_click(lambda _: self.snap_upright())
        self.delete.on_click(lambda _: self.remove_pose())
        self.undo.on_click(lambda _: state.undo() or app.say("Nothing to undo."))
        self.redo.on_click(lambda _: state.redo() or app.say("Nothing to redo."))
        self.face_box.on_update(self._on_face_box)
        app.scene.gizmo.on_update(self._on_gizmo)
        self._hook_faces()

        app.add_command("Undo", "Z", lambda: state.undo(), modifier="cmd/ctrl")
        app.add_command("Redo", "Y", lambda: state.redo(), modifier="cmd/ctrl")
        app.add_command("Fit box to points", "G", self.fit_to_points, description="shrink or grow the box to the points inside it")
        app.add_command("Snap upright", "U", self.snap_upright, description="symmetric categories: the box's y on the object's axis, the free turn canonical")

    # --- sync from the state -------------------------------------------------------------
    def sync(self, extents, category: str, symmetry: str) -> None:
        """Show the document's values (called inside ``app.syncing()``)."""
        for number, value in zip(self.extent_inputs, extents):
            number.value = float(round(value * 1000, 1))
        self.category.value = category
        self.symmetry.value = symmetry

    # --- actions -------------------------------------------------------------------------
    def _box(self):
        return self.app.state.box()

    def place_here(self) -> None:
        position, orientation, _, _ = self._box()
        self.app.commit_box(position, orientation)

    def remove_pose(self) -> None:
        state = self.app.state
        frame_id = state.frame_id
        if not state.has_pose(frame_id):
            self.app.say("This frame has no pose.")
            return
        state.edit(lambda doc: doc.frames.pop(frame_id, None))

    def fit_to_points(self) -> None:
        """Fit the box to the frame's full-resolution points inside it (grown by 1 cm), orientation kept."""
        app = self.app
        position, orientation, extents, _ = self._box()
        cloud = frame_points(app.sequence, app.state.frame, box=(position, orientation, extents), margin=0.01)
        fitted = box_edits.fit_to_points(cloud.points, position, orientation, extents, margin=0.0, trim=0.002)
        if fitted is None:
            app.say("Fit: fewer than 10 points inside the box.")
            return
        app.commit_box(fitted[0], orientation, extents=fitted[1])
        app.say(f"Fitted the box to {len(cloud)} points.")

    def snap_upright(self) -> None:
        """Symmetric categories: the box's y on the symmetry axis estimated from the points (when the tracking
        engine offers the estimate), and the unobservable turn about it made canonical (object +z towards the camera).

        The points are this frame's inside the box plus the accumulated points of the posed frames, which
        see the object from more sides than one frame does.
        """
        app = self.app
        if app.state.document().symmetry != "y":
            app.say("Snap upright is for symmetric categories (symmetry y).")
            return
        position, orientation, extents, _ = self._box()
        up = None
        try:
            from .tracking import estimate_axis  # the tracking engine's axis estimate, when present
        except ImportError:
            estimate_axis = None
        if estimate_axis is not None:
            from .app_model import accumulate_model

            cloud = frame_points(app.sequence, app.state.frame, box=(position, orientation, extents), margin=0.005)
            document = app.state.document()
            model, _ = accumulate_model(app.sequence, document)
            R = quat_to_matrix(orientation)
            points = np.vstack([cloud.points, model @ R.T + position])
            try:
                up = estimate_axis(points, position, orientation, extents)
            except Exception as error:  # an estimate that fails leaves the current axis
                app.say(f"Axis estimate failed ({error}); kept the box's axis.")
            if up is not None and np.degrees(np.arccos(np.clip(abs(np.dot(up, R[:, 1])), -1, 1))) > MAX_AXIS_SNAP_DEG:
                app.say(f"The estimated axis is more than {MAX_AXIS_SNAP_DEG:.0f} degrees off the box's: kept the box's axis.")
                up = None
        app.commit_box(position, box_edits.upright_about_y(position, orientation, up))

    def _on_category(self, event) -> None:
        if self.app.is_syncing:
            return
        self.app.state.set_category(event.target.value)

    def _on_symmetry(self, event) -> None:
        if self.app.is_syncing:
            return
        symmetry = event.target.value
        self.app.state.edit(lambda doc: setattr(doc, "symmetry", symmetry))

    def _on_extent(self, axis: int, value_mm: float) -> None:
        if self.app.is_syncing:
            return
        value = float(value_mm) / 1000.0
        if not np.isfinite(value) or value <= 0 or abs(value - self.app.state.document().extents[axis]) < 1e-7:
            return
        self.app.state.set_extent(axis, value)

    def _on_face_box(self, event) -> None:
        self.app.scene.set_face_handles(bool(event.target.value))

    def _on_gizmo(self, event) -> None:
        """Commit the gizmo's pose when a drag ends (one undo step per drag)."""
        if getattr(event, "phase", "end") != "end":
            return
        target = event.target
        self.app.commit_box(np.asarray(target.position, dtype=np.float64), xyzw(target.wxyz))

    def _hook_faces(self) -> None:
        for name, axis, sign in FACES:
            self.app.scene.face_handles[name].on_update(lambda event, axis=axis, sign=sign: self._on_face(event, axis, sign))

    def _on_face(self, event, axis: int, sign: int) -> None:
        """A face handle was dragged: move that face by the drag along its normal, the opposite face stays."""
        if getattr(event, "phase", "end") != "end":
            return
        position, orientation, extents, _ = self._box()
        rest = sign * extents[axis] / 2
        distance = sign * (float(np.asarray(event.target.position)[axis]) - rest)  # outward, metres
        new_position, new_extents = box_edits.drag_face(position, orientation, extents, axis, sign, distance)
        self.app.commit_box(new_position, orientation, extents=new_extents)
        self.app.scene.place_face_handles(new_extents)  # back on the faces, also when the size did not change
