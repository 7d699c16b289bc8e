"""An annotator's work, measured: a suite sequence from nothing to exported ground truth in headless Chromium.

    .venv/bin/python benchmarks/bench_annotator.py [--sequence dev-mug-pattern] [--frames 100] [--data DIR] [--engine chains]

The browser tool (``annotate SEQ``) in a subprocess, driven through its page as a person would, with the truth
standing in for the person's eyes: choose the category; in 3 frames (one per third of the sequence, where the object
is in view: the first where it stands most upright, the others where it looks most like there) click the object, make adjustments (each the single typed turn, 90 degree
turn or flip that brings the box nearest the truth, as the person would see it; two in the first box, which every
other is refined against, one in the others; none where the box is within 2 deg), and refine (not the first: there is
no other box yet); track all frames; review the worst flagged frames (next flagged, then accept what is right or
refine what is not; at most 3, within the budget of 25 interactions); export. Every click, key and typed field counts
as one interaction. Prints the interactions, the wall time per step, the boxes' errors, and the accuracy of the
document and of the export (annotations.json, REDWOOD75's format) against the truth.

The goal (issue 49): a new 100-frame sequence to exported ground truth in at most 25 interactions and 3 minutes of a
person's time. The wall time here includes the server's tracking and export and a software-rendered page on a shared
machine; the person's own time is the interactions.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from annotate import box_edits  # noqa: E402
from annotate.app_state import NEW_DOCUMENT_CATEGORY  # noqa: E402
from annotate.process import start as start_annotate  # noqa: E402
from annotate.app_review import is_flagged  # noqa: E402
from evaluate.geometry import raw_to_shapenet_pose  # noqa: E402
from evaluate.metrics.pose_errors import rotation_error, translation_error  # noqa: E402
from sequences.annotation import load_annotation  # noqa: E402
from sequences.reader import open_sequence  # noqa: E402
from sequences.sample import cache_dir  # noqa: E402
from sequences.truth import Truth, open_truth  # noqa: E402

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
VIEWPORT = {"width": 1280, "height": 800}
#: The frames the person annotates, one per third of the sequence.
BOXES = 3
#: Flagged frames the person reviews at most, worst first, ...
REVIEWED = 3
#: ... within this many interactions in all (the goal), the export's two included.
BUDGET = 25
#: Adjustments in the first box (the object frame every other box is refined against) and in each other.
FIRST_ADJUSTMENTS, ADJUSTMENTS = 2, 2
#: An adjustment is worth making while the box's turn is further off than this (deg).
ADJUST_ABOVE_DEG = 2.0
#: A pose the person would call right (deg, m): accepted in review.
RIGHT_DEG, RIGHT_M = 5.0, 0.01
#: Seconds to wait for the server's long steps (tracking, export) on a loaded machine.
LONG_S = 1800.0


# --- what the person sees --------------------------------------------------------------------------------------------
def upright_tilt_deg(T: np.ndarray) -> float:
    """How far (deg) the object's up (+y) is from the image's up (camera -y)."""
    return float(np.degrees(np.arccos(np.clip(-T[1, 1], -1.0, 1.0))))


def object_pixel(truth: Truth, frame_id: str) -> tuple[np.ndarray, int]:
    """A pixel (u, v) on the visible object nearest its middle (where a person clicks), and the visible area (px)."""
    mask = truth.mask(frame_id)
    vs, us = np.nonzero(mask)
    if not len(us):
        return np.array([np.nan, np.nan]), 0
    k = np.argmin((us - us.mean()) ** 2 + (vs - vs.mean()) ** 2)
    return np.array([us[k], vs[k]], dtype=float), len(us)


def to_page(uv: np.ndarray, camera, canvas: dict) -> tuple[float, float]:
    """A sensor pixel's position on the page: the viewer looks from the sensor with its vertical field of view."""
    scale = canvas["height"] / camera.height
    return (canvas["x"] + canvas["width"] / 2 + (uv[0] - camera.cx) * scale, canvas["y"] + canvas["height"] / 2 + (uv[1] - camera.cy) * scale)


def choose_frames(truth: Truth, ids: list[str], camera, canvas: dict, panel_left: float, count: int = BOXES) -> list[int]:
    """Per part of the sequence a frame where the object is well in view and its middle lies left of the panel: in the
    first part where it stands most upright, in the others where it looks most like there (a person picks frames
    where the object shows the sides the first box was fitted to: the box carried over needs the fewest turns, and
    the refine finds the surfaces the first box holds)."""
    chosen: list[int] = []
    for part in np.array_split(np.arange(len(ids)), count):
        best, best_score = int(part[len(part) // 2]), np.inf
        for k in part[len(part) // 6 : len(part) - len(part) // 6 : 2]:  # not at a part's ends: the boxes spread
            uv, area = object_pixel(truth, ids[k])
            if area < 1500 or to_page(uv, camera, canvas)[0] > panel_left - 20:
                continue
            T = truth.poses[ids[k]]
            if chosen:
                score = float(rotation_error(truth.poses[ids[chosen[0]]][:3, :3], T[:3, :3], truth.symmetry))
            else:
                score = upright_tilt_deg(T)
            if score < best_score:
                best, best_score = int(k), score
        chosen.append(best)
    return chosen


@dataclass
class Adjustment:
    """One adjustment a person makes: what, the keys or field values, the interactions it takes, the predicted turn
    error after it (deg)."""

    name: str
    steps: list[tuple[str, str]] = field(default_factory=list)  # ("key", "Alt+j") or ("type", "12")
    error_deg: float = 0.0

    @property
    def interactions(self) -> int:
        return len(self.steps)


def best_adjustment(orientation, truth_T: np.ndarray, symmetry: str) -> Adjustment:
    """The single adjustment (a typed turn about one camera axis, a 90 degree turn or flip about a box axis, or none)
    that brings the box's turn nearest the truth."""
    R_true = truth_T[:3, :3]

    def error(q) -> float:
        return float(rotation_error(R_true, Rotation.from_quat(q).as_matrix(), symmetry))

    best = Adjustment("none", [], error(orientation))
    for axis, key in ((0, "1"), (1, "2"), (2, "3")):
        q = box_edits.turn(orientation, axis, 180.0)
        if error(q) < best.error_deg - 1.0:
            best = Adjustment(f"flip about box {'xyz'[axis]}", [("key", key)], error(q))
    for axis, key in ((0, "4"), (1, "5"), (2, "6")):
        q = box_edits.turn(orientation, axis, 90.0)
        if error(q) < best.error_deg - 1.0:
            best = Adjustment(f"turn 90 about box {'xyz'[axis]}", [("key", key)], error(q))
    # a typed angle about a camera axis: Alt+ keys turn by it (about y: J +; about x: K +; about z: P +)
    keys = {0: "Alt+k", 1: "Alt+j", 2: "Alt+p"}
    angles = np.arange(-180, 181, 1.0)
    for axis in range(3):
        for turn, where, step in ((box_edits.turn_camera, "camera", ("key", keys[axis])), (box_edits.turn, "box", ("box", f"{'xyz'[axis]}+"))):
            errors = [error(turn(orientation, axis, a)) for a in angles]
            k = int(np.argmin(errors))
            if errors[k] < best.error_deg - 2.0 and angles[k] != 0:
                best = Adjustment(f"typed {angles[k]:.0f} deg about {where} {'xyz'[axis]}", [("type", f"{angles[k]:.0f}"), step], errors[k])
    return best


def apply_adjustment(orientation, adjustment: Adjustment) -> np.ndarray:
    """The orientation after ``adjustment`` (as the page does it)."""
    q = np.asarray(orientation, dtype=np.float64)
    angle = 0.0
    for kind, value in adjustment.steps:
        if kind == "type":
            angle = float(value)
        elif kind == "box":
            q = box_edits.turn(q, "xyz".index(value[0]), angle)
        elif value in ("1", "2", "3"):
            q = box_edits.turn(q, int(value) - 1, 180.0)
        elif value in ("4", "5", "6"):
            q = box_edits.turn(q, int(value) - 4, 90.0)
        else:
            q = box_edits.turn_camera(q, {"Alt+k": 0, "Alt+j": 1, "Alt+p": 2}[value], angle)
    return q


# --- the person ---------------------------------------------------------------------------------------------------------
class Person:
    """A page and a count of what the person did on it."""

    def __init__(self, page, document: Path) -> None:
        self.page = page
        self.document = document
        self.interactions = 0
        self.log: list[str] = []

    def _did(self, what: str) -> None:
        self.interactions += 1
        self.log.append(what)

    def text(self) -> str:
        return self.document.read_text() if self.document.exists() else ""

    def wait_for_change(self, before: str, timeout: float = 120.0, missing_ok: bool = False) -> str:
        """The document once it differs from ``before``; with ``missing_ok`` the same after ``timeout`` s (an edit that
        left it as it was)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            now = self.text()
            if now != before:
                return now
            time.sleep(0.1)
        if missing_ok:
            return before
        raise TimeoutError(f"{self.document} did not change within {timeout} s")

    def click(self, locator, what: str) -> None:
        locator.click()
        self._did(f"click {what}")

    def key(self, key: str) -> None:
        self.page.keyboard.press(key)
        self._did(f"key {key}")

    def click_at(self, x: float, y: float, what: str) -> None:
        self.page.mouse.click(x, y)
        self._did(f"click {what} at ({x:.0f}, {y:.0f})")

    def type_into(self, label: str, value: str) -> None:
        field_ = self.page.get_by_label(label, exact=True).first
        field_.fill(value)
        field_.press("Enter")
        field_.evaluate("e => e.blur()")  # leaving the field: the keys go to the page again
        self._did(f"type {value} into {label}")

    def choose(self, label: str, option: str) -> None:
        self.click(self.page.get_by_label(label, exact=True).first, label)
        self.click(self.page.get_by_role("option", name=option, exact=True).first, option)

    def wait_text(self, pattern: str, timeout: float = 120.0) -> None:
        """Until the page shows text matching the regular expression ``pattern`` (case matters)."""
        self.page.get_by_text(re.compile(pattern)).first.wait_for(timeout=timeout * 1000)


def errors_against(poses: dict[str, np.ndarray], truth: Truth) -> dict:
    """Rotation (deg, symmetry as the truth's) and centre (mm) errors of poses (frame id -> 4x4) against the truth."""
    ids = [f for f in poses if f in truth.poses]
    rot = np.array([rotation_error(truth.poses[f][:3, :3], poses[f][:3, :3], truth.symmetry) for f in ids])
    ctr = np.array([translation_error(truth.poses[f][:3, 3], poses[f][:3, 3]) for f in ids]) * 1000
    return {"frames": len(ids), "rot_median_deg": float(np.median(rot)), "rot_p90_deg": float(np.percentile(rot, 90)),
            "centre_median_mm": float(np.median(ctr)), "centre_p90_mm": float(np.percentile(ctr, 90)),
            "within_5deg_1cm": float(np.mean((rot <= 5) & (ctr <= 10))), "within_10deg_2cm": float(np.mean((rot <= 10) & (ctr <= 20)))}


def exported_poses(out: Path, name: str, sequence) -> dict[str, np.ndarray]:
    """The exported poses (ShapeNet axes) by frame id, from annotations.json's rgb files."""
    entry = json.loads((out / "annotations.json").read_text())[name]
    by_file = {Path(sequence.frames[k].color_path).name: f for k, f in enumerate(sequence.ids)}
    poses = {}
    for ann in entry["pose_anns"]:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(ann["orientation"]).as_matrix()
        T[:3, 3] = ann["position"]
        poses[by_file[ann["rgb_file"]]] = raw_to_shapenet_pose(T)
    return poses


def annotate_like_a_person(page, root: Path, truth: Truth, url: str) -> dict:
    """Drive the page from a new document to an export (see the module's docstring); returns the figures."""
    sequence = open_sequence(root)
    ids, camera = sequence.ids, sequence.camera
    document = root / "annotation.yaml"
    person = Person(page, document)
    stages: dict[str, float] = {}
    t0 = time.perf_counter()
    page.goto(url + "/?fixedDpr=0.5")
    person.wait_text(r"frame 1/\d+", 300)
    page.evaluate("document.querySelectorAll('.mantine-Notification-root, .mantine-Notifications-notification').forEach(e => e.remove())")
    canvas = page.locator("canvas").first.bounding_box()
    panel = page.get_by_text("Guide: workflow and hotkeys", exact=False).first.bounding_box()
    panel_left = panel["x"] - 20 if panel else canvas["x"] + canvas["width"]
    stages["open"] = time.perf_counter() - t0

    # the category: the box takes its typical size (a new document's own category needs no choosing: nothing changes)
    t = time.perf_counter()
    if (load_annotation(document).category if document.exists() else NEW_DOCUMENT_CATEGORY) != truth.category:
        before = person.text()
        person.choose("Category", truth.category)
        person.wait_for_change(before)
    frames = choose_frames(truth, ids, camera, canvas, panel_left)
    adjustments, boxes = [], []
    current = 0
    for n, index in enumerate(frames):
        frame_id = ids[index]
        if index != current:
            _go_to(person, index)
            person.wait_text(rf"frame {index + 1}/\d+")
            current = index
        uv, _ = object_pixel(truth, frame_id)
        x, y = to_page(uv, camera, canvas)
        before = person.text()
        person.click_at(x, y, f"the object in frame {index + 1}")
        before = person.wait_for_change(before)
        orientation = load_annotation(document).frames[frame_id].orientation
        made = []
        for _ in range(FIRST_ADJUSTMENTS if n == 0 else ADJUSTMENTS):
            adjustment = best_adjustment(orientation, truth.poses[frame_id], truth.symmetry)
            if not adjustment.steps:
                break
            if rotation_error(truth.poses[frame_id][:3, :3], Rotation.from_quat(orientation).as_matrix(), truth.symmetry) <= ADJUST_ABOVE_DEG:
                break
            for kind, value in adjustment.steps:
                if kind == "type":
                    person.type_into("Turn by (°)", value)
                elif kind == "box":
                    turn_box = page.get_by_text("Turn about box", exact=True).first.locator("xpath=ancestor::div[contains(@class, 'mantine-Flex-root')][1]")
                    person.click(turn_box.get_by_role("button", name=value, exact=True).first, f"Turn about box {value}")
                    before = person.wait_for_change(before)
                else:
                    person.key(value)
                    before = person.wait_for_change(before)
            orientation = apply_adjustment(orientation, adjustment)
            made.append(adjustment.name)
        adjustments.append(made)
        if n > 0:  # (the first has no other box to refine against)
            person.key("r")
            _wait_refine(person, before)
        placed = load_annotation(document).frames[frame_id]
        boxes.append((index + 1, round(float(rotation_error(truth.poses[frame_id][:3, :3], placed.matrix[:3, :3], truth.symmetry)), 1),
                      round(float(translation_error(truth.poses[frame_id][:3, 3], placed.position)) * 1000, 1), placed.source))
    stages["place"] = time.perf_counter() - t

    t = time.perf_counter()
    before = person.text()
    person.click(page.get_by_role("button", name="Track all frames").first, "Track all frames")
    person.wait_text(r"Tracked \d+ frames in", LONG_S)
    stages["track"] = time.perf_counter() - t

    t = time.perf_counter()
    doc = load_annotation(document)
    flagged = sum(1 for p in doc.frames.values() if is_flagged(p))
    reviewed = []
    for _ in range(min(REVIEWED, flagged)):
        if person.interactions + 2 + 2 > BUDGET:
            break
        previous = shown_frame(page)
        person.key("f")
        index = _settled_frame(page, previous, -1, timeout=30.0)  # the next flagged frame, once the page shows it
        frame_id = ids[index]
        pose = load_annotation(document).frames[frame_id]
        rot = rotation_error(truth.poses[frame_id][:3, :3], pose.matrix[:3, :3], truth.symmetry)
        ctr = translation_error(truth.poses[frame_id][:3, 3], pose.position)
        before = person.text()
        if rot <= RIGHT_DEG and ctr <= RIGHT_M:
            person.key("c")
            person.wait_for_change(before)
            reviewed.append((index + 1, "accepted"))
        else:
            person.key("r")
            _wait_refine(person, before)
            reviewed.append((index + 1, "refined"))
    stages["review"] = time.perf_counter() - t

    t = time.perf_counter()
    out = root.resolve().parent / f"{sequence.name}_gt"
    person.click(page.get_by_text("Model and export", exact=True).first, "Model and export")
    person.click(page.get_by_role("button", name="Export ground truth").first, "Export ground truth")
    person.wait_text(r"Exported ground truth to", LONG_S)
    stages["export"] = time.perf_counter() - t
    wall = time.perf_counter() - t0

    doc = load_annotation(document)
    return {
        "sequence": sequence.name, "frames": len(ids), "category": truth.category, "interactions": person.interactions,
        "wall_s": wall, "stages_s": stages, "boxes_in": [k + 1 for k in frames], "adjustments": adjustments, "boxes": boxes,
        "flagged_after_tracking": flagged, "reviewed": reviewed,
        "document": errors_against({f: p.matrix for f, p in doc.frames.items()}, truth),
        "export": errors_against(exported_poses(out, sequence.name, sequence), truth),
        "log": person.log,
    }


def _go_to(person: Person, index: int) -> None:
    """Type the frame's number into the field beside the frame slider (then N / B if it did not land there)."""
    page = person.page
    field_ = page.locator(".mantine-Slider-root").first.locator("xpath=..").locator("input:not([type=hidden])").first
    field_.fill(str(index + 1))
    field_.press("Enter")
    field_.evaluate("e => e.blur()")
    person._did(f"type {index + 1} into the frame field")
    start = shown_frame(page)
    for _ in range(8):
        shown = _settled_frame(page, start, index)
        if shown == index:
            return
        person.key("n" if shown < index else "b")
        start = shown
    raise RuntimeError(f"the page went to frame {shown_frame(page) + 1}, not {index + 1}")


def _settled_frame(page, start: int, wanted: int, timeout: float = 60.0, still: float = 1.0) -> int:
    """The frame the page shows (0-based) once it shows ``wanted``, or once it has left ``start`` and stayed on another
    frame for ``still`` s (or after ``timeout`` s), as a person waits for the page before pressing again: a slow page
    is no reason for another key."""
    deadline = time.monotonic() + timeout
    last, since = start, time.monotonic()
    while time.monotonic() < deadline:
        shown = shown_frame(page)
        if shown == wanted:
            return shown
        if shown != last:
            last, since = shown, time.monotonic()
        elif shown != start and time.monotonic() - since >= still:
            return shown
        time.sleep(0.1)
    return shown_frame(page)


def shown_frame(page) -> int:
    """The frame the page's title shows (0-based)."""
    title = page.get_by_text(re.compile(r"frame \d+/\d+, id")).first.inner_text()
    return int(re.search(r"frame (\d+)/", title).group(1)) - 1


def _wait_refine(person: Person, before: str) -> None:
    """Until the refine changed the document or said it left the box as it was."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if person.text() != before or person.page.get_by_text("Refine left the box", exact=False).count():
            return
        time.sleep(0.1)
    raise TimeoutError("refine did not answer")


def suite_sequence(name: str, frames: int, data: Path) -> Path:
    from benchmarks.suite.spec import build, load_suite

    suite = load_suite()
    return build(next(e for e in suite.entries if e.name == name), frames, data)


def run(source: Path, engine: str | None = None, keep: Path | None = None) -> dict:
    """Copy the sequence (no document), serve it, annotate it in headless Chromium; the figures."""
    from playwright.sync_api import sync_playwright

    work = Path(tempfile.mkdtemp(prefix="bench_annotator_"))
    try:
        root = work / source.name
        shutil.copytree(source, root, ignore=shutil.ignore_patterns("annotation.yaml*", "*_gt"))
        truth = open_truth(root)
        server, url = start_annotate([root, "--port", "0"], work / "annotate.log", timeout=300, environment={"REDWOOD_GT_ENGINE": engine} if engine else None)
        try:
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True)
                try:
                    page = browser.new_page(viewport=VIEWPORT)
                    page.set_default_timeout(300_000)
                    try:
                        figures = annotate_like_a_person(page, root, truth, url)
                    finally:
                        if keep is not None:
                            page.screenshot(path=str(keep))
                finally:
                    browser.close()
        finally:
            server.stop()
        return figures
    finally:
        shutil.rmtree(work, ignore_errors=True)


def report(figures: dict) -> str:
    d, e = figures["document"], figures["export"]
    stages = ", ".join(f"{k} {v:.0f} s" for k, v in figures["stages_s"].items())
    return "\n".join([
        f"{figures['sequence']} ({figures['frames']} frames, {figures['category']}): {figures['interactions']} interactions, {figures['wall_s']:.0f} s wall ({stages})",
        f"  boxes in frames {figures['boxes_in']}, adjustments {figures['adjustments']}; {figures['flagged_after_tracking']} flagged after tracking, reviewed {figures['reviewed']}",
        f"  the boxes placed (frame, deg, mm, source): {figures['boxes']}",
        f"  document vs truth: rotation median {d['rot_median_deg']:.2f} / p90 {d['rot_p90_deg']:.2f} deg, centre median {d['centre_median_mm']:.1f} / p90 {d['centre_p90_mm']:.1f} mm, "
        f"within 5 deg 1 cm {d['within_5deg_1cm']:.0%}, 10 deg 2 cm {d['within_10deg_2cm']:.0%} ({d['frames']} frames)",
        f"  export vs truth:   rotation median {e['rot_median_deg']:.2f} / p90 {e['rot_p90_deg']:.2f} deg, centre median {e['centre_median_mm']:.1f} / p90 {e['centre_p90_mm']:.1f} mm, "
        f"within 5 deg 1 cm {e['within_5deg_1cm']:.0%}, 10 deg 2 cm {e['within_10deg_2cm']:.0%} ({e['frames']} frames)",
    ])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequence", default="dev-mug-pattern", help="a suite sequence's name, or a sequence folder with truth/")
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--data", default=str(cache_dir() / "suite"), help="cache of generated suite sequences")
    parser.add_argument("--engine", default=None, help="tracking engine (default: annotate.engines' choice)")
    parser.add_argument("--screenshot", default=None, help="keep the page's last view here")
    parser.add_argument("--log", action="store_true", help="print every interaction")
    args = parser.parse_args()
    source = Path(args.sequence) if Path(args.sequence).is_dir() else suite_sequence(args.sequence, args.frames, Path(args.data))
    figures = run(source, args.engine, Path(args.screenshot) if args.screenshot else None)
    print(report(figures))
    if args.log:
        print("\n".join(f"  {k + 1:2d}. {line}" for k, line in enumerate(figures["log"])))


if __name__ == "__main__":
    main()
