"""``annotate [SEQ]``: the browser annotation tool (viser).

:class:`App` ties the shared session (:mod:`.app_state`), the display frames (:mod:`.app_frames`),
the 3D scene (:mod:`.app_scene`), the 2D views (:mod:`.app_views`), the guide (:mod:`.app_guide`) and the
panels for placing by pointing (:mod:`.app_placing`), editing the box (:mod:`.app_editing`), moving and turning it
(:mod:`.app_moving`), tracking (:mod:`.app_tracking`), review (:mod:`.app_review`) and the
model (:mod:`.app_model`); :mod:`.app_serve` starts it. All GUI and scene elements are the server's, so every
browser tab shows the same state; only the viewer camera is per tab. The page counts frames from 1; the session
(``AppState.frame``) from 0.
"""

from __future__ import annotations

import contextlib
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np
import viser

from sequences.reader import Sequence

from .app_editing import EditingPanel
from .app_frames import FrameCache
from .app_guide import Hotkey, guide_markdown, key_label
from .app_model import ModelPanel
from .app_moving import MovePanel
from .app_placing import PlacingPanel
from .app_review import ReviewPanel, mark_fixed, reviewed_count
from .app_scene import SceneView
from .app_state import AppState
from .app_tracking import TrackingPanel
from .app_views import draw_box, sensor_view, timeline_image, timeline_legend


#: The view button's label by state: what a click does (False: not looking through the camera).
LOOK_LABELS = {False: "Look through camera", True: "Leave camera view"}
#: Moving the viewer this far (m) from the sensor leaves the view through the camera ...
LOOK_LEAVE_M = 0.02
#: ... once this long (s) after entering it (the tab's camera reports from before may still arrive).
LOOK_SETTLE_S = 1.0


class App:
    """The annotation tool on one viser server."""

    def __init__(self, server: viser.ViserServer, sequence: Sequence, document: str | Path | None = None, stride: int = 2) -> None:
        self.server = server
        self.sequence = sequence
        self.state = AppState(sequence, document)
        self.cache = FrameCache(sequence, stride=stride)
        self.render_lock = threading.RLock()
        self._local = threading.local()
        self.look_through = False
        self._look_since = 0.0  # when the view through the camera was entered (time.monotonic)
        self.hotkeys: list[Hotkey] = []  # every command's key, for the guide
        first = self.cache.get(0)
        point_size = 1.3 * stride * first.median_depth / sequence.camera.fx  # about the pixel footprint
        self.scene = SceneView(server, sequence.camera, point_size=point_size)
        self.view = sensor_view(sequence.camera, first.median_depth)
        server.initial_camera.position = self.view["position"]
        server.initial_camera.look_at = self.view["look_at"]
        server.initial_camera.up = self.view["up"]
        server.initial_camera.fov = self.view["fov"]
        server.initial_camera.near = 0.01

        gui = server.gui
        server.gui.configure_theme(control_width="large")
        self.title = gui.add_markdown(f"**{sequence.name}**: {len(sequence)} frames")
        self.tabs = gui.add_markdown("")  # how many other tabs share this session
        self._clients: set[int] = set()
        self.message = gui.add_markdown("")
        with gui.add_folder("Guide: workflow and hotkeys", expand_by_default=self.state.is_new):
            self.guide = gui.add_markdown("")
        with gui.add_folder("Frame"):
            # frames are numbered from 1 on the page, as in the title
            self.frame_slider = gui.add_slider("Frame", min=1, max=max(len(sequence), 2), step=1, initial_value=1,
                                               hint=f"frame number, 1 to {len(sequence)}")
            self.prev_button = gui.add_button(key_label("Previous frame", "B"))
            self.next_button = gui.add_button(key_label("Next frame", "N"))
            self.timeline = gui.add_image(timeline_image(self.state.statuses(), 0), label="Timeline", format="png")
            gui.add_markdown(timeline_legend())
            self.overlay = gui.add_image(first.image[::2, ::2], label="Colour image and box", format="jpeg", jpeg_quality=85)
        self.placing = PlacingPanel(self)
        self.editing = EditingPanel(self)
        self.moving = MovePanel(self)
        self.tracking = TrackingPanel(self)
        self.review = ReviewPanel(self)
        self.model = ModelPanel(self)
        with gui.add_folder("View"):
            self.look_button = gui.add_button(key_label(LOOK_LABELS[False], "H"))
            # off at first: seen from the sensor, the frustum's image plane would cover the whole view
            self.frustum_box = gui.add_checkbox("Show camera", initial_value=False, hint="the camera frustum with the colour image")
            # the range follows the data: a sequence 3 m away has points a centimetre apart
            size_mm = round(point_size * 1000 * 2) / 2 if np.isfinite(point_size) else 1.0
            largest = max(10.0, np.ceil(2 * size_mm))
            self.point_slider = gui.add_slider("Point size (mm)", min=0.5, max=largest, step=0.5, initial_value=float(np.clip(size_mm, 0.5, largest)),
                                               hint="the points' size in the 3D view")

        self.frame_slider.on_update(self._on_slider)
        self.prev_button.on_click(lambda _: self.state.step(-1))
        self.next_button.on_click(lambda _: self.state.step(1))
        self.look_button.on_click(lambda event: self.look_through_camera(event.client))
        self.frustum_box.on_update(self._on_frustum)
        self.point_slider.on_update(self._on_point_size)
        self.add_command("Next frame", "N", lambda: self.state.step(1))
        self.add_command("Previous frame", "B", lambda: self.state.step(-1))
        self.add_command("Look through camera", "H", self.look_through_camera, with_client=True,
                         description="view from the sensor, the colour image behind the points; H again, or orbiting, leaves")
        self.guide.content = guide_markdown(self.hotkeys)

        self.state.subscribe(self._on_change)
        self.state.on_error = self.say
        server.on_client_connect(self._on_connect)
        server.on_client_disconnect(self._on_disconnect)
        self.redraw("frame")
        if self.state.read_only:
            self.say(self.state.read_only)

    # --- helpers -------------------------------------------------------------------------
    @contextlib.contextmanager
    def syncing(self):
        """While the app writes GUI values itself, their update callbacks must not edit the document."""
        previous = getattr(self._local, "syncing", False)
        self._local.syncing = True
        try:
            yield
        finally:
            self._local.syncing = previous

    @property
    def is_syncing(self) -> bool:
        return getattr(self._local, "syncing", False)

    def add_command(self, label: str, key: str, action: Callable, modifier: str | None = None, description: str | None = None,
                    with_client: bool = False) -> None:
        """A hotkey (a viser command, also in its palette): ``action()``, or ``action(client)`` with ``with_client``."""
        command = self.server.gui.add_command(label, hotkey=key, modifier=modifier, description=description)
        if with_client:
            command.on_trigger(lambda event: action(event.client))
        else:
            command.on_trigger(lambda _: action())
        self.hotkeys.append(Hotkey(label, key, modifier))

    @staticmethod
    def key_label(label: str, key: str, modifier: str | None = None) -> str:
        """A button's label with its hotkey (see app_guide.key_label)."""
        return key_label(label, key, modifier)

    def say(self, text: str) -> None:
        """One line of feedback at the top of the panel (every tab)."""
        self.message.content = text

    def commit_box(self, position, orientation, extents=None, source: str = "manual", extra: dict | None = None) -> None:
        """Set the current frame's pose (and optionally the extents) as one undoable, saved change."""
        from sequences.annotation import FramePose

        position = np.asarray(position, dtype=np.float64)
        orientation = np.asarray(orientation, dtype=np.float64)
        orientation = orientation / np.linalg.norm(orientation)
        if not (np.all(np.isfinite(position)) and np.all(np.isfinite(orientation))):
            self.say("Ignored a pose with a NaN value.")
            return
        frame_id = self.state.frame_id

        def change(doc) -> None:
            doc.frames[frame_id] = FramePose(position.copy(), orientation.copy(), source, mark_fixed(doc.frames.get(frame_id), extra or {}))
            if extents is not None:
                doc.extents = np.asarray(extents, dtype=np.float64).copy()

        self.state.edit(change)

    # --- drawing -------------------------------------------------------------------------
    def _on_change(self, kind: str) -> None:
        self.redraw(kind)

    def redraw(self, kind: str = "document") -> None:
        """Bring the scene and the panels up to date with the session (kind: "frame" or "document")."""
        with self.render_lock:
            state = self.state
            with state.lock:
                index = state.frame
                pose, own = state.pose()
                extents = state.annotation.extents.copy()
                status = state.status()
                statuses = state.statuses()
                review = state.review()
                reviewed = reviewed_count(state.annotation)
                annotation = state.annotation
                category, symmetry = annotation.category, annotation.symmetry
            frame = self.cache.get(index)
            # half size: enough for the panel and the frustum, a quarter of the drawing and encoding
            image = draw_box(frame.image[::2, ::2], self.sequence.camera, pose.position, pose.orientation, extents, scale=0.5)
            with self.server.atomic():
                if kind == "frame":
                    self.scene.show_frame(frame, image)
                else:
                    self.scene.show_image(image, frame.median_depth)
                self.scene.show_pose(pose.position, pose.orientation)
                self.scene.show_box(extents, own)
                self.overlay.image = image
                self.timeline.image = timeline_image(statuses, index)
                with self.syncing():
                    self.frame_slider.value = index + 1
                    self.editing.sync(extents, category, symmetry)
                frame_id = self.sequence.frames[index].id
                note = "" if own else " (no pose yet: showing the nearest frame's box; click the object to place it, or any edit places it here)"
                checked = f", reviewed ({pose.extra['reviewed']})" if own and pose.extra.get("reviewed") else ""
                self.title.content = f"**{self.sequence.name}**: frame {index + 1}/{len(self.sequence)}, id {frame_id}, **{status}**{checked}{note}"
                self.tracking.sync(pose, own, review, index)
                self.review.sync(review, index, reviewed)
            if self.look_through:
                self.scene.server.scene.set_background_image(frame.image, format="jpeg")

    # --- callbacks -----------------------------------------------------------------------
    def _on_slider(self, event) -> None:
        if not self.is_syncing:
            self.state.set_frame(int(event.target.value) - 1)  # the page counts from 1

    def _on_frustum(self, event) -> None:
        if self.scene.frustum is not None:
            self.scene.frustum.visible = bool(event.target.value)

    def _on_point_size(self, event) -> None:
        self.scene.point_size = float(event.target.value) / 1000.0
        self.redraw("frame")

    def _on_connect(self, client: viser.ClientHandle) -> None:
        with self.render_lock:
            self._clients.add(client.client_id)
            self._show_tabs()
        self.set_client_view(client)
        client.camera.on_update(self._on_camera)

    def _on_camera(self, camera) -> None:
        """Orbiting away from the sensor leaves the view through the camera (its backdrop belongs to the sensor's view)."""
        if self.look_through and time.monotonic() - self._look_since > LOOK_SETTLE_S:
            if np.linalg.norm(np.asarray(camera.position) - self.view["position"]) > LOOK_LEAVE_M:
                self.look_through_camera(None)

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        with self.render_lock:
            self._clients.discard(client.client_id)
            self._show_tabs()

    def _show_tabs(self) -> None:
        """Every tab sees the same session: say how many others share it (the count is the same in each tab)."""
        others = len(self._clients) - 1
        if others <= 0:
            self.tabs.content = ""
        else:
            self.tabs.content = (f"**{others} other tab{'s' if others > 1 else ''}** open on this session: "
                                 "all tabs share the document, the frame and undo.")

    def set_client_view(self, client: viser.ClientHandle | None) -> None:
        """Put a tab's viewer camera at the sensor, looking at the data with the sensor's field of view."""
        if client is None:
            return
        with client.atomic():
            client.camera.up_direction = self.view["up"]
            client.camera.position = self.view["position"]
            client.camera.look_at = self.view["look_at"]
            client.camera.fov = self.view["fov"]

    def look_through_camera(self, client: viser.ClientHandle | None) -> None:
        """Toggle the view through the sensor: viewer camera at the sensor, the colour image behind the points. The
        button's label says what a click does next."""
        self.look_through = not self.look_through
        self._look_since = time.monotonic()
        self.look_button.label = key_label(LOOK_LABELS[self.look_through], "H")
        if self.look_through:
            clients = [client] if client is not None else list(self.server.get_clients().values())
            for c in clients:
                self.set_client_view(c)
            self.scene.frustum.visible = False
            self.server.scene.set_background_image(self.cache.get(self.state.frame).image, format="jpeg")
            self.say("Looking through the camera (H again, or orbit, to leave).")
        else:
            self.server.scene.set_background_image(None)
            self.scene.frustum.visible = bool(self.frustum_box.value)
            self.say("")

    def close(self) -> None:
        self.tracking.close()
        self.model.close()
        self.cache.close()
        self.state.close()
