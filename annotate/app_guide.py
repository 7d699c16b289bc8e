"""The on-page guide: the workflow in six steps, and the hotkeys (those the panels registered, so it lists every one).

Hotkeys are viser commands (also in its command palette, cmd/ctrl+K); buttons that have one carry it in their label,
as viser 1.1's client shows no tooltip on buttons (the inputs' tooltips work).
"""

from __future__ import annotations

from dataclasses import dataclass

#: The workflow, one line per step: (step, what to do).
WORKFLOW = (
    ("Place", "choose the category (Box): the box takes its typical size. In a frame where the object is clear, click "
              "it in the 3D view (or look through the camera, H, and click it in the colour image): the box lands on it, "
              "fitted to the depth there, and it stays on that surface while you turn it. Shift+drag a rectangle around the object to give its outline (its size). "
              "Then set it right: Shift+J/L, I/K, O/P move it as you see it (left/right, up/down, toward/away), Alt+ the same "
              "keys turn it by Turn by, "
              "the gizmo moves and turns it, a face's arrow moves that face (a frame without its own box shows the "
              "nearest one's, grey and without handles: click the object to place it there). The green face is the top (+y, "
              "labelled), the blue one the front, a mug's handle side (-z). Do this in 2-3 frames spread over the sequence."),
    ("Refine", "R registers the box to the frame's points and the other posed frames: a box that is close snaps on; "
               "where it cannot, the box stays and the page says why."),
    ("Track", "Track all frames gives every frame a pose from your boxes: placed, refined and accepted boxes are its "
              "anchors and stay as they are (the Tracking panel lists them before a run, and what changed after it)."),
    ("Review", "the Review list holds the flagged frames, worst first: F goes to the next; fix the box (then R), or "
               "accept it (C) when it is right, or reject it (X)."),
    ("Preview", "Model and export > Preview mesh carves the posed frames: do the boxes agree?"),
    ("Export", "Export ground truth writes annotations.json and the mesh (REDWOOD75's format)."),
)


#: How the page writes viser's modifiers and special keys.
MODIFIER_NAMES = {"cmd/ctrl": "Ctrl", "alt": "Alt", "shift": "Shift"}
KEY_NAMES = {"arrowleft": "←", "arrowright": "→", "arrowup": "↑", "arrowdown": "↓", "pageup": "PgUp", "pagedown": "PgDn"}


@dataclass(frozen=True)
class Hotkey:
    """A command's key: ``label`` (what it does), ``key`` (a letter or digit), ``modifier`` (viser's, e.g. "cmd/ctrl")."""

    label: str
    key: str
    modifier: str | None = None

    @property
    def shown(self) -> str:
        """The key as the page writes it: "N", "Ctrl+Z", "Shift+←", "PgUp"."""
        prefix = "".join(f"{MODIFIER_NAMES[part]}+" for part in (self.modifier or "").split("+") if part)
        return prefix + KEY_NAMES.get(self.key, self.key)


def key_label(label: str, key: str, modifier: str | None = None) -> str:
    """A button's label with its hotkey: "Next frame (N)"."""
    return f"{label} ({Hotkey(label, key, modifier).shown})"


def guide_markdown(hotkeys: list[Hotkey]) -> str:
    """The guide: numbered workflow steps, then the hotkeys, two columns."""
    steps = "\n".join(f"{k}. **{step}**: {text}" for k, (step, text) in enumerate(WORKFLOW, start=1))
    rows = "\n".join(f"| {h.shown} | {h.label} |" for h in hotkeys)
    return (f"{steps}\n\nFrames are numbered from 1. Every change is saved at once; Ctrl+Z undoes it.\n\n"
            f"| key | action |\n|---|---|\n{rows}\n\nKeys go to the page while no field has the focus: click a blank part of the panel after typing.")
