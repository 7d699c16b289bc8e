"""The move-and-turn panel: steps of the box along and about its own axes and the camera's, by a chosen step.

Moves go by the step in millimetres, along the box's x, y, z or as the annotator sees the box: left/right, up/down,
toward/away from the camera (annotate.box_edits.nudge_camera). Turns go by a typed angle (1, 5 and 90 degrees one
click away) about the box's axes or the camera's (box_edits.turn_camera); flips turn 180 degrees about the box's.
Each click or key is one undoable change of the document. A box placed by a click stays on the surface clicked while
it is turned (fitted again at each turn: the box's reach toward the camera changes with its turn) until it is moved.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from . import box_edits, box_placing

if TYPE_CHECKING:
    from .app import App

NUDGE_STEPS_MM = ("1", "2", "5", "10", "20")
#: Keys that move the box along its x, y, z: (minus, plus).
MOVE_KEYS = (("J", "L"), ("K", "I"), ("O", "P"))
#: Camera moves, keys with Shift (the box moves' keys): (label, camera axis, sign, key): right is camera +x, down +y,
#: away +z (along the ray). Not the arrow keys: viser's viewer moves its camera while an arrow key (or W, A, S, D, Q,
#: E) is held, whatever else the key does.
CAMERA_MOVES = (("left", 0, -1, "J"), ("right", 0, 1, "L"), ("up", 1, -1, "I"), ("down", 1, 1, "K"), ("toward", 2, -1, "O"), ("away", 2, 1, "P"))
#: Turn steps one click away (degrees).
TURN_STEPS_DEG = ("1", "5", "90")
#: Camera turns by Turn by, the same keys with Alt: (label, camera axis, sign, key). About the camera's y (down), +:
#: the box's front turns to the left as seen; about x (right), +: its top turns toward the camera; about z (the
#: view), +: clockwise as seen.
CAMERA_TURNS = (("left", 1, 1, "J"), ("right", 1, -1, "L"), ("top away", 0, -1, "I"), ("top toward", 0, 1, "K"),
                ("anticlockwise", 2, -1, "O"), ("clockwise", 2, 1, "P"))
TURN_BUTTONS = ("x-", "x+", "y-", "y+", "z-", "z+")


class MovePanel:
    """GUI for stepping the current frame's box: moves along box or camera axes, turns about them."""

    def __init__(self, app: "App") -> None:
        self.app = app
        gui = app.server.gui
        with gui.add_folder("Move and turn"):
            self.step = gui.add_dropdown("Move step (mm)", NUDGE_STEPS_MM, initial_value="2", hint="how far a move button or key moves the box")
            self.camera_move = gui.add_button_group("Move as seen", tuple(label for label, *_ in CAMERA_MOVES),
                                                    hint="relative to the camera; keys Shift+J, L, I, K, O (toward), P (away)")
            self.move = [gui.add_button_group(f"Move along box {a}", ("-", "+"), hint=f"along the box's own {a} axis; keys {minus} and {plus}")
                         for a, (minus, plus) in zip("xyz", MOVE_KEYS)]
            self.turn_by = gui.add_number("Turn by (°)", initial_value=5.0, min=-360.0, max=360.0, step=0.5,
                                          hint="the angle of a turn button or key, degrees (type any)")
            self.turn_step = gui.add_button_group("Turn step (°)", TURN_STEPS_DEG, hint="sets Turn by")
            self.turn_box = gui.add_button_group("Turn about box", TURN_BUTTONS, hint="by Turn by about the box's own axes (y: its up)")
            self.turn_camera = gui.add_button_group("Turn about camera", TURN_BUTTONS,
                                                    hint="by Turn by about the camera's axes: x right, y down, z the view; keys Alt+J, L, I, K, O, P")
            self.turn90 = gui.add_button_group("Turn 90° about box", ("x", "y", "z"), hint="about the box's own axes; keys 4, 5, 6")
            self.flip180 = gui.add_button_group("Flip 180° about box", ("x", "y", "z"), hint="about the box's own axes; keys 1, 2, 3")

        self.camera_move.on_click(lambda event: self.nudge_camera(*self._camera_move(event.target.value)))
        for axis, group in enumerate(self.move):
            group.on_click(lambda event, axis=axis: self.nudge(axis, 1 if event.target.value == "+" else -1))
        self.turn_step.on_click(lambda event: setattr(self.turn_by, "value", float(event.target.value)))
        self.turn_box.on_click(lambda event: self.turn(*self._turn(event.target.value)))
        self.turn_camera.on_click(lambda event: self.turn_seen(*self._turn(event.target.value)))
        self.turn90.on_click(lambda event: self.turn("xyz".index(event.target.value), 90.0))
        self.flip180.on_click(lambda event: self.turn("xyz".index(event.target.value), 180.0))

        for label, axis, sign, key in CAMERA_MOVES:
            app.add_command(f"Move {label} (as seen)", key, lambda axis=axis, sign=sign: self.nudge_camera(axis, sign), modifier="shift")
        for label, axis, sign, key in CAMERA_TURNS:
            app.add_command(f"Turn {label} (as seen)", key, lambda axis=axis, sign=sign: self.turn_seen(axis, sign * float(self.turn_by.value)), modifier="alt")
        for axis, (minus, plus) in enumerate(MOVE_KEYS):
            app.add_command(f"Move -{'xyz'[axis]} (box)", minus, lambda axis=axis: self.nudge(axis, -1))
            app.add_command(f"Move +{'xyz'[axis]} (box)", plus, lambda axis=axis: self.nudge(axis, 1))
        for axis in range(3):
            app.add_command(f"Flip 180° about box {'xyz'[axis]}", str(axis + 1), lambda axis=axis: self.turn(axis, 180.0))
            app.add_command(f"Turn 90° about box {'xyz'[axis]}", str(axis + 4), lambda axis=axis: self.turn(axis, 90.0))

    def _camera_move(self, label: str) -> tuple[int, int]:
        _, axis, sign, _ = next(m for m in CAMERA_MOVES if m[0] == label)
        return axis, sign

    def _turn(self, label: str) -> tuple[int, float]:
        """A turn button ("y-") as (axis, signed degrees by Turn by)."""
        return "xyz".index(label[0]), (1.0 if label[1] == "+" else -1.0) * float(self.turn_by.value)

    @property
    def step_m(self) -> float:
        return float(self.step.value) / 1000.0

    def nudge(self, axis: int, sign: int) -> None:
        """Move the box by the step along its own ``axis``."""
        position, orientation, _, _ = self.app.state.box()
        self.app.commit_box(box_edits.nudge(position, orientation, axis, sign * self.step_m), orientation)

    def nudge_camera(self, axis: int, sign: int) -> None:
        """Move the box by the step as seen: camera ``axis`` 0 right, 1 down, 2 away (``sign`` -1 the other way)."""
        position, orientation, _, _ = self.app.state.box()
        self.app.commit_box(box_edits.nudge_camera(position, axis, sign * self.step_m), orientation)

    def turn(self, axis: int, degrees: float) -> None:
        """Turn the box by ``degrees`` about its own ``axis``."""
        position, orientation, extents, _ = self.app.state.box()
        self._commit_turn(position, box_edits.turn(orientation, axis, degrees), extents)

    def turn_seen(self, axis: int, degrees: float) -> None:
        """Turn the box by ``degrees`` about the camera's ``axis`` through its centre."""
        position, orientation, extents, _ = self.app.state.box()
        self._commit_turn(position, box_edits.turn_camera(orientation, axis, degrees), extents)

    def _commit_turn(self, position, orientation, extents) -> None:
        """Commit a turned box: about its centre, or, while it rests on a clicked surface, fitted to it again."""
        app = self.app
        state = app.state
        point = state.contact_point()
        if point is None:
            app.commit_box(position, orientation)
            return
        frame_id = state.frame_id
        fit = box_placing.place_on_surface(app.cache.get(state.frame).depth, app.sequence.camera, point, orientation, extents)
        app.commit_box(fit.position, orientation)
        state.set_contact(frame_id, point, fit.position)
