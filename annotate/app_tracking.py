"""The tracking panel: refine this frame, track a range or everything (in the background, with progress).
Reviewing the flagged frames is the review panel's (app_review).

A refine that fails leaves the box as it was and says why (app_refine). A run keeps the boxes a person placed,
refined or accepted, says which before it runs, and lists the frames it moved after (app_anchors). The engine is
annotate.engines' choice; without it the panel says so and the rest of the tool keeps working.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from sequences.annotation import Annotation, FramePose

from .app_anchors import anchors, changes_markdown, engine_view, keep_markdown, on_the_track, pose_changes, restore_anchors
from .app_refine import engine_config, judge_refine
from .app_review import Flagged, is_flagged

if TYPE_CHECKING:
    from .app import App


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
            self.keeps = gui.add_markdown("")  # what a run will keep, before it runs
            self.progress = gui.add_progress_bar(0.0, animated=False)
            self.info = gui.add_markdown("")
            self.changes = gui.add_markdown("")  # what the last run changed
        self.refine.on_click(lambda _: self.refine_current())
        self.track_range.on_click(lambda _: self.start_tracking(int(self.range_from.value) - 1, int(self.range_to.value) - 1))
        self.track_all.on_click(lambda _: self.start_tracking(0, n - 1))
        self.range_from.on_update(lambda _: self.show_keeps())
        self.range_to.on_update(lambda _: self.show_keeps())
        app.add_command("Refine this frame", "R", self.refine_current, description="register the box to the points and the model of the other frames")
        if tracking_engine() is None:
            self.info.content = "Tracking engine (annotate.tracking) is not installed: refine and track are unavailable."

    # --- shown state ---------------------------------------------------------------------
    def range_ids(self, first: int | None = None, last: int | None = None) -> list[str]:
        """The frame ids of a run from index ``first`` to ``last`` (default: the range fields), in order."""
        n = len(self.app.sequence)
        first = int(self.range_from.value) - 1 if first is None else first
        last = int(self.range_to.value) - 1 if last is None else last
        first, last = sorted((int(np.clip(first, 0, n - 1)), int(np.clip(last, 0, n - 1))))
        return self.app.sequence.ids[first : last + 1]

    def show_keeps(self) -> None:
        """Say what a run will keep: over all frames, and over the range fields' range where that differs."""
        state, ids = self.app.state, self.app.sequence.ids
        with state.lock:
            document = state.annotation
            text = keep_markdown(document, ids, ids)
            chosen = self.range_ids()
            if len(chosen) != len(ids):
                text = f"Track all frames: {text}\n\nTrack range: {keep_markdown(document, chosen, ids)}"
        self.keeps.content = text

    def sync(self, pose: FramePose, own: bool, review: list[Flagged], index: int) -> None:
        """Say what the current frame's pose is, and why it is flagged (in words, with its rank in the review list)."""
        self.show_keeps()
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
        self.info.content = (f"**Flagged**{where}: {reason}. Fix the box (then Refine), or Accept (C) if it is right.")

    @property
    def busy(self) -> bool:
        return self.worker is not None and self.worker.is_alive()

    # --- actions -------------------------------------------------------------------------
    def refine_current(self) -> None:
        """Refine the current frame's box (starting from the box shown) and store it as ``refined``; where the refine
        fails (app_refine.judge_refine) the box stays as it was and the page says why."""
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
        if not any(f != frame_id for f in document.frames):
            self.say_refine("Refine left the box as it was: it fits the box to the object the other posed frames show, "
                            "and this is the only one. Place a box in another frame (or track), then refine.")
            return
        if not own:
            document.frames[frame_id] = FramePose(pose.position.copy(), pose.orientation.copy(), "manual")
        config = engine_config(engine)
        start = time.perf_counter()
        try:
            result = engine.refine_frame(app.sequence, document, frame_id, config)
        except Exception as error:  # a failed registration must not take the page down
            self.say_refine(f"Refine left the box as it was: it failed ({error}).")
            return
        self.last_refine_s = time.perf_counter() - start
        if state.frame_id != frame_id:
            return  # the annotator moved on; a stale result must not land on another frame
        verdict = judge_refine(result, config)
        number = f"frame {state.frame + 1}"
        if not verdict.ok:
            self.say_refine(f"Refine left the box of {number} as it was: {verdict.reason}.")
            return
        app.commit_box(result.position, result.orientation, source=result.source or "refined", extra=result.extra)
        flagged = f" It is flagged: {verdict.reason}." if verdict.reason else ""
        app.say(f"Refined {number} (id {frame_id}) in {self.last_refine_s * 1000:.0f} ms.{flagged}")

    def say_refine(self, text: str) -> None:
        """A refine's outcome on the page, at the top and in this panel (the box did not change: no redraw clears it)."""
        self.app.say(text)
        self.info.content = text

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
        ids = self.range_ids(first, last)
        document = app.state.document()
        kept = anchors(document, ids)
        if not kept:
            app.say("Tracking needs a box a person placed, refined or accepted in the range: place one first.")
            return False
        self.progress.value = 0.0
        self._running = True
        self.worker = threading.Thread(target=self._track, args=(engine, document, ids, kept), name="tracking", daemon=True)
        self.worker.start()
        if wait:
            self.worker.join()
        return True

    def _track(self, engine, document: Annotation, ids: list[str], kept: list[str]) -> None:
        """The run: the engine sees the anchors as placed boxes and gives them back as anchors (app_anchors); the
        frames an annotator changed while it ran keep the annotator's boxes."""
        app = self.app
        start = time.perf_counter()
        self.info.content = f"Tracking {len(ids)} frames from {len(kept)} kept boxes..."
        for button in (self.track_all, self.track_range, self.refine):
            button.disabled = True

        def progress(done: int, total: int) -> None:
            self.progress.value = 100.0 * done / max(total, 1)

        try:
            result = engine.track_sequence(app.sequence, engine_view(document, kept), frames=ids, progress=progress)
            result = restore_anchors(result, document, kept)
        except Exception as error:
            self._running = False
            app.say(f"Tracking failed: {error}")
            self.info.content = ""
            return
        finally:
            for button in (self.track_all, self.track_range, self.refine):
                button.disabled = False
        self._running = False
        taken: list[str] = []

        def change(doc: Annotation) -> None:
            # the tracked frames, but not those an annotator changed meanwhile (nor, outside the range, any frame)
            taken.clear()
            for frame_id in ids:
                if frame_id in result.frames and _same(doc.frames.get(frame_id), document.frames.get(frame_id)):
                    doc.frames[frame_id] = result.frames[frame_id]
                    taken.append(frame_id)

        all_ids = app.sequence.ids
        app.state.edit(change)
        after = app.state.document()
        changed, new = pose_changes(document, after, taken, all_ids)
        flagged = sum(1 for f in taken if is_flagged(after.frames[f]))
        skipped = len(ids) - len(taken) - sum(1 for f in ids if f not in result.frames)
        followed = sum(1 for f in kept if f in taken and on_the_track(document.frames[f], after.frames[f]))
        kept_note = (f" The {len(kept)} box{'es' if len(kept) != 1 else ''} placed, refined or accepted stay the anchors; {followed} took the "
                     "pose the other frames agree on (each box kept beside it).")
        edited = f" {skipped} frames changed while it ran keep your boxes." if skipped else ""
        summary = f"Tracked {len(ids)} frames in {time.perf_counter() - start:.1f} s; {flagged} flagged for review.{kept_note}{edited}"
        self.changes.content = "Last run: " + changes_markdown(changed, new)
        self.info.content = summary
        self.progress.value = 100.0
        app.say(summary + (" The Review list holds them, worst first (F: next)." if flagged else ""))

    def close(self) -> None:
        pass


def _same(a: FramePose | None, b: FramePose | None) -> bool:
    """Whether two poses of a frame are the same box (both absent, or equal pose and source)."""
    if a is None or b is None:
        return a is b
    return a.source == b.source and np.array_equal(a.position, b.position) and np.array_equal(a.orientation, b.orientation)
