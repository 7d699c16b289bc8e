"""Review: the flagged frames, worst first, each with its reason in words; "next flagged" walks that list.

A frame's severity is how far its worst quality figure lies beyond the tracking engine's review threshold for it
(``annotate.tracking.config.TrackingConfig``): 2.0 is a figure twice its limit (a chain departure of 16 deg where
8 is allowed, a fitness of 0.25 where 0.5 is needed). A flagged frame counts at least 1.0 (flagged for a reason
no figure measures, e.g. lying between flagged frames); an error or no points at all is the worst there is.
Ties keep the sequence's order. The reason shown is the engine's ``flag_reason`` (its first clause, the rest
counted). A frame the annotator accepted (``reviewed: accepted``) or fixed (``reviewed: fixed``) is no longer
flagged (:func:`is_flagged`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from sequences.annotation import Annotation, FramePose

if TYPE_CHECKING:
    from .app import App

#: Figures beyond a threshold, by (figure, TrackingConfig field): larger is worse.
ABOVE = (
    ("chain_disagreement_deg", "max_chain_disagreement_deg"), ("chain_disagreement_m", "max_chain_disagreement_m"),
    ("chains_jumped_deg", "max_chain_disagreement_deg"), ("chains_jumped_m", "max_chain_disagreement_m"),
    ("chain_departure_deg", "max_chain_departure_deg"), ("rotation_jump_deg", "max_frame_rotation_deg"),
    ("manual_correction_deg", "max_manual_correction_deg"), ("manual_correction_m", "max_manual_correction_m"),
    ("inlier_rmse", "max_inlier_rmse"),
    ("refine_rejected_deg", "max_refine_step_deg"), ("refine_rejected_m", "max_refine_step_m"),
)
#: ... and below one: smaller is worse.
BELOW = (("fitness", "min_fitness"), ("second_chain_fitness", "min_fitness"), ("in_box", "min_in_box"), ("points", "min_points"))
#: Severity of a frame whose figures could not be measured at all (an error, no points).
WORST = 100.0
#: Flagged frames listed on the page (the rest are counted).
SHOWN = 8
#: The key that accepts a pose: C (correct). Not E: viser's viewer moves its camera while W, A, S, D, Q, E or an arrow
#: key is held, whatever else the key does.
ACCEPT_KEY = "C"
#: ``reviewed`` values: the annotator said the pose is right, or changed it by hand after it was flagged.
REVIEWED = ("accepted", "fixed")


def is_flagged(pose: FramePose) -> bool:
    """Whether the tracking engine flagged this pose for review (``flagged: true`` or a non-empty ``flags``) and no
    one has reviewed it since."""
    extra = pose.extra
    if extra.get("reviewed") in REVIEWED:
        return False
    return bool(extra.get("flagged")) or bool(extra.get("flags"))


def mark_fixed(old: FramePose | None, extra: dict) -> dict:
    """The extra keys of a pose a person just gave a frame: ``reviewed: fixed`` when the frame's pose was flagged and
    the new one is not (a refine that fails again leaves it flagged)."""
    extra = dict(extra)
    if old is not None and is_flagged(old) and not (extra.get("flagged") or extra.get("flags")):
        extra["reviewed"] = "fixed"
    return extra


def review_thresholds():
    """The tracking engine's review thresholds (a TrackingConfig), or None without the engine."""
    try:
        from .tracking.config import TrackingConfig
    except ImportError:
        return None
    return TrackingConfig()


def severity(pose: FramePose, thresholds=None) -> float:
    """How far beyond its review thresholds a flagged frame's worst figure lies (>= 1; see the module's docstring)."""
    extra = pose.extra
    if extra.get("error"):
        return WORST
    worst = 1.0
    if thresholds is None:
        return worst
    for figure, limit_name in ABOVE:
        value, limit = extra.get(figure), getattr(thresholds, limit_name, 0)
        if _number(value) and limit > 0:
            worst = max(worst, abs(float(value)) / limit)
    for figure, limit_name in BELOW:
        value, limit = extra.get(figure), getattr(thresholds, limit_name, 0)
        if _number(value) and limit > 0:
            worst = max(worst, WORST if value <= 0 else min(limit / float(value), WORST))
    return worst


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def plain_reason(pose: FramePose) -> str:
    """The engine's reason for the flag in words: its first clause, and how many more there are."""
    reasons = [r.strip() for r in str(pose.extra.get("flag_reason") or "").split(";") if r.strip()]
    if not reasons:
        return "the tracking engine marked it for review"
    more = f" (and {len(reasons) - 1} more)" if len(reasons) > 1 else ""
    return reasons[0] + more


@dataclass(frozen=True)
class Flagged:
    """A frame to review: its index in the sequence (0-based), id, severity and reason."""

    index: int
    frame_id: str
    severity: float
    reason: str


def review_list(annotation: Annotation, ids: list[str], thresholds=None) -> list[Flagged]:
    """The flagged frames of ``annotation`` (frame ids in sequence order ``ids``), worst first, ties in sequence order."""
    items = [Flagged(i, f, severity(annotation.frames[f], thresholds), plain_reason(annotation.frames[f]))
             for i, f in enumerate(ids) if f in annotation.frames and is_flagged(annotation.frames[f])]
    return sorted(items, key=lambda item: (-item.severity, item.index))


def next_in_review(order: list[int], current: int) -> int | None:
    """The frame after ``current`` in the review ``order`` (indices, worst first; wrapping), or its first when
    ``current`` is not in it; None when it is empty."""
    if not order:
        return None
    if current not in order:
        return order[0]
    return order[(order.index(current) + 1) % len(order)]


def reviewed_count(annotation: Annotation) -> int:
    """Frames the annotator accepted or fixed after they were flagged."""
    return sum(1 for pose in annotation.frames.values() if pose.extra.get("reviewed"))


def review_markdown(items: list[Flagged], current: int, reviewed: int) -> str:
    """The review list for the page: the worst :data:`SHOWN` frames (1-based numbers), the current one in bold."""
    done = f" {reviewed} reviewed." if reviewed else ""
    if not items:
        return f"No flagged frames.{done}"
    lines = [f"**{len(items)} flagged**, worst first (F: next).{done}"]
    for rank, item in enumerate(items[:SHOWN], start=1):
        text = f"{rank}. frame {item.index + 1}: {item.reason}"
        lines.append(f"**{text}**" if item.index == current else text)
    if len(items) > SHOWN:
        lines.append(f"... and {len(items) - SHOWN} more")
    return "\n\n".join(lines)


class ReviewPanel:
    """GUI for reviewing: the flagged frames worst first, next flagged, accept, reject."""

    def __init__(self, app: "App") -> None:
        self.app = app
        gui = app.server.gui
        with gui.add_folder("Review"):
            self.list = gui.add_markdown("")
            self.next_flagged = gui.add_button(app.key_label("Next flagged frame", "F"))
            self.accept = gui.add_button(app.key_label("Accept pose", ACCEPT_KEY))
            self.reject = gui.add_button(app.key_label("Reject pose", "X"))
        self.next_flagged.on_click(lambda _: self.goto_next_flagged())
        self.accept.on_click(lambda _: self.accept_current())
        self.reject.on_click(lambda _: self.reject_current())
        app.add_command("Next flagged frame", "F", self.goto_next_flagged, description="the next frame of the review list, worst first")
        app.add_command("Accept pose", ACCEPT_KEY, self.accept_current, description="this frame's pose is right: clear its flag")
        app.add_command("Reject pose", "X", self.reject_current, description="remove this frame's pose (place or track it again)")

    def sync(self, items: list[Flagged], current: int, reviewed: int) -> None:
        """Show the review list (called on every redraw)."""
        self.list.content = review_markdown(items, current, reviewed)

    def goto_next_flagged(self) -> None:
        index = self.app.state.next_flagged()
        if index is None:
            self.app.say("No flagged frame.")
        else:
            self.app.state.set_frame(index)

    def accept_current(self) -> None:
        """Mark the current frame's pose as reviewed and right (its flag is cleared)."""
        state = self.app.state
        frame_id = state.frame_id
        if not state.has_pose(frame_id):
            self.app.say("This frame has no pose to accept.")
            return

        def change(doc) -> None:
            pose = doc.frames.get(frame_id)  # another tab may have removed it since
            if pose is not None:
                pose.extra.pop("flagged", None)
                pose.extra["reviewed"] = "accepted"

        state.edit(change)

    def reject_current(self) -> None:
        """Remove the current frame's pose (tracked wrongly); place or track it again."""
        state = self.app.state
        frame_id = state.frame_id
        if not state.has_pose(frame_id):
            self.app.say("This frame has no pose to reject.")
            return
        state.edit(lambda doc: doc.frames.pop(frame_id, None))
