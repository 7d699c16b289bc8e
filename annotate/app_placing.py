"""Placing the box by pointing: a click on the object puts the box there, a Shift+drag around it gives its outline.

A click in the 3D view (or, looking through the camera, in the colour image behind the points) is a ray from the
viewer; the box (the shown one's orientation, the document's extents: the category's typical ones until someone
sizes it) lands on the surface it hits, fitted to the depth around it (annotate.box_placing), and stays on it while it
is turned (the state's contact; app_moving) until it is moved. A rectangle dragged with Shift is the object's
outline as seen: it sets the sides across the view too. Each is one undoable change.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from . import box_placing

if TYPE_CHECKING:
    from .app import App

#: The modifier that turns a drag in the 3D view into an outline (a plain drag orbits).
OUTLINE_MODIFIER = "shift"


def viewer_camera(camera) -> tuple:
    """A viser client's camera as box_placing's (R, t, fov, aspect): its wxyz is the world-from-camera rotation
    (OpenCV axes), its position the camera's centre, fov vertical in radians."""
    w, x, y, z = np.asarray(camera.wxyz, dtype=np.float64)
    R = Rotation.from_quat([x, y, z, w]).as_matrix()
    return R, np.asarray(camera.position, dtype=np.float64), float(camera.fov), float(camera.aspect)


class PlacingPanel:
    """Scene clicks and outlines that place the current frame's box."""

    def __init__(self, app: "App") -> None:
        self.app = app
        gui = app.server.gui
        with gui.add_folder("Place by pointing"):
            self.enabled = gui.add_checkbox("Click places the box", initial_value=True,
                                            hint="a click on the object in the 3D view puts the box there; Shift+drag: its outline")
            gui.add_markdown("Click the object (or look through the camera, H, and click it in the colour image). "
                             "**Shift+drag** a rectangle around it to give its outline, which sizes the box.")
        scene = app.server.scene
        scene.on_click()(self._on_click)
        scene.on_rect_select(modifier=OUTLINE_MODIFIER)(self._on_outline)

    def _on_click(self, event) -> None:
        if self.enabled.value:
            self.place_on_ray(event.ray_origin, event.ray_direction)

    def _on_outline(self, event) -> None:
        if self.enabled.value:
            self.place_in_outline(event.screen_min, event.screen_max, viewer_camera(event.client.camera))

    def place_on_ray(self, origin, direction) -> bool:
        """Put the box on the surface the ray (world = the current frame's camera frame) hits; False when none."""
        app = self.app
        frame = app.cache.get(app.state.frame)
        hit = box_placing.pick_on_ray(frame.points, origin, direction)
        if hit is None:
            app.say("No depth under the click: click on the object itself.")
            return False
        _, orientation, extents, _ = app.state.box()
        frame_id = app.state.frame_id
        fit = box_placing.place_on_surface(frame.depth, app.sequence.camera, hit, orientation, extents)
        app.commit_box(fit.position, orientation)
        app.state.set_contact(frame_id, hit, fit.position)
        app.say(f"Placed the box where you clicked, fitted to {fit.points} points of the surface there: turn it if needed (it "
                "stays on that surface until you move it), then Refine (R).")
        return True

    def place_in_outline(self, screen_min, screen_max, camera: tuple) -> bool:
        """Size and place the box from an outline (screen rectangle, 0..1) of a viewer ``camera`` (R, t, fov, aspect)."""
        app = self.app
        frame = app.cache.get(app.state.frame)
        _, orientation, extents, _ = app.state.box()
        fitted = box_placing.outline_box(frame.points, camera, np.asarray(screen_min, float), np.asarray(screen_max, float), orientation, extents)
        if fitted is None:
            app.say("No depth inside the outline: drag around the object.")
            return False
        position, new_extents = fitted
        app.commit_box(position, orientation, extents=new_extents)
        mm = " x ".join(f"{v * 1000:.0f}" for v in new_extents)
        app.say(f"Placed the box in the outline: {mm} mm (x, y, z). Refine (R) next.")
        return True
