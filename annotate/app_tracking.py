"""The tracking panel: refine this frame, track a range or everything (in the background, with progress).
Reviewing the flagged frames is the review panel's (app_review).

The engine is :mod:`annotate.tracking` (issue 5); without it the panel says so and the rest of
the tool keeps working.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING

from sequences.annotation import FramePose

from .app_review import Flagged, is_flagged

if TYPE_CHECKING:
    from .app import App

#: Posed frames (twice the nearest used) that the interactive refine builds its model from.
REFINE_MODEL_FRAMES = 6


def tracking_engine():
    """The tracking engine's module (annotate.engines: $REDWOOD_GT_ENGINE or the default), or None when it is not
    installed."""
    from .engines import tracking_engine as chosen

    try:
        tracking = chosen()
    except (ImportError, ValueError):
        return None
    if not (hasattr(tracking, "refine_frame") and hasattr(tracking, "track_sequence")):
        return None
    return tracking


class TrackingPanel:
    """GUI for the tracking engine; long runs happen in a worker thread, one at a time."""

    def __init__(self, app: "App") -> None:
        self.app = app
        self.worker: threading.Thread | None = None
        self.last_refine_s: float | None = None
        self._running = False  # a run's progress line stays until its result is in
        n = len(app.sequence)
        gui = app.server.gui
        with gui.add_folder("Tracking"):
            self.refine = gui.add_button(app.key_label("Refine this frame", "R"))
            # frame numbers count from 1 on the page
            self.range_from = gui.add_number("Track from frame", initial_value=1, min=1, max=max(n, 1), step=1, hint="first frame of the range (from 1)")
            self.range_to = gui.add_number("Track to frame", initial_value=max(n, 1), min=1, max=max(n, 1), step=1, hint=f"last frame of the range (up to {n})")
            self.track_range = gui.add_button("Track range")
            self.track_all = gui.add_button("Track all frames")
            self.progress = gui.add_progress_bar(0.0, animated=False)
            self.info = gui.add_markdown("")
        self.refine.on_click(lambda _: self.refine_current())
        self.track_range.on_click(lambda _: self.start_tracking(int(self.range_from.value) - 1, int(self.range_to.value) - 1))
        self.track_all.on_click(lambda _: self.start_tracking(0, n - 1))
        app.add_command("Refine this frame", "R", self.refine_current, description="register the box to the points and the model of the other frames")
        if tracking_engine() is None:
            self.info.content = "Tracking engine (annotate.tracking) is not installed: refine and track are unavailable."

    # --- shown state ---------------------------------------------------------------------
    def sync(self, pose: FramePose, own: bool, review: list[Flagged], index: int) -> None:
        """Say what the current frame's pose is, and why it is flagged (in words, with its rank in the review list)."""
        if self._running:
            return
        if not own:
            self.info.content = "No pose in this frame yet."
            return
        if not is_flagged(pose):
            self.info.content = f"Pose: {pose.source}."
            return
        rank = next((k for k, item in enumerate(review, start=1) if item.index == index), None)
        where = f" (#{rank} of {len(review)} in the review list)" if rank else ""
        reason = str(pose.extra.get("flag_reason") or "the tracking engine marked it for review")
        self.info.content = (f"**Flagged**{where}: {reason}. Fix the box (then Refine), or Accept (E) if it is right.")

    @property
    def busy(self) -> bool:
        return self.worker is not None and self.worker.is_alive()

    # --- actions -------------------------------------------------------------------------
    @staticmethod
    def refine_config(engine):
        """Interactive refine: a model from the few nearest posed frames only (each is read from disk per call)."""
        config_class = getattr(engine, "TrackingConfig", None)
        return None if config_class is None else config_class(max_global_frames=REFINE_MODEL_FRAMES)

    def refine_current(self) -> None:
        """Refine the current frame's box (starting from the box shown) and store it as ``refined``."""
        app = self.app
        engine = tracking_engine()
        if engine is None:
            app.say("Refine needs the tracking engine (annotate.tracking), which is not installed.")
            return
        state = app.state
        with state.lock:
            frame_id = state.frame_id
            pose, own = state.pose()
            document = state.annotation.copy()
        if not own:
            document.frames[frame_id] = FramePose(pose.position.copy(), pose.orientation.copy(), "manual")
        start = time.perf_counter()
        try:
            result = engine.refine_frame(app.sequence, document, frame_id, self.refine_config(engine))
        except Exception as error:  # a failed registration must not take the page down
            app.say(f"Refine failed: {error}")
            return
        self.last_refine_s = time.perf_counter() - start
        if state.frame_id != frame_id:
            return  # the annotator moved on; a stale result must not land on another frame
        app.commit_box(result.position, result.orientation, source=result.source or "refined", extra=result.extra)
        app.say(f"Refined frame {state.frame + 1} (id {frame_id}) in {self.last_refine_s * 1000:.0f} ms.")

    def start_tracking(self, first: int, last: int, wait: bool = False) -> bool:
        """Track frames ``first``..``last`` (indices) in a worker thread; the result is one undoable change."""
        app = self.app
        engine = tracking_engine()
        if engine is None:
            app.say("Tracking needs the tracking engine (annotate.tracking), which is not installed.")
            return False
        if self.busy:
            app.say("Tracking is already running.")
            return False
        first, last = sorted((max(first, 0), min(last, len(app.sequence) - 1)))
        ids = app.sequence.ids[first : last + 1]
        document = app.state.annotation.copy()
        self.progress.value = 0.0
        self._running = True
        self.worker = threading.Thread(target=self._track, args=(engine, document, ids), name="tracking", daemon=True)
        self.worker.start()
        if wait:
            self.worker.join()
        return True

    def _track(self, engine, document, ids: list[str]) -> None:
        app = self.app
        start = time.perf_counter()
        self.info.content = f"Tracking {len(ids)} frames..."
        for button in (self.track_all, self.track_range, self.refine):
            button.disabled = True

        def progress(done: int, total: int) -> None:
            self.progress.value = 100.0 * done / max(total, 1)

        try:
            result = engine.track_sequence(app.sequence, document, frames=ids, progress=progress)
        except Exception as error:
            self._running = False
            app.say(f"Tracking failed: {error}")
            self.info.content = ""
            return
        finally:
            for button in (self.track_all, self.track_range, self.refine):
                button.disabled = False
        self._running = False

        def change(doc) -> None:
            # take the tracked frames; edits made meanwhile to frames outside the range are kept
            for frame_id in ids:
                if frame_id in result.frames:
                    doc.frames[frame_id] = result.frames[frame_id]

        flagged = sum(1 for f in ids if f in result.frames and is_flagged(result.frames[f]))
        summary = f"Tracked {len(ids)} frames in {time.perf_counter() - start:.1f} s; {flagged} flagged for review."
        self.info.content = summary  # the progress line goes; the redraw of the edit then shows the frame's pose
        app.state.edit(change)
        self.progress.value = 100.0
        app.say(summary + (" The Review list holds them, worst first (F: next)." if flagged else ""))

    def close(self) -> None:
        pass
