"""Responsiveness of the annotation app, server side: switching frames and refining a frame.

Goals (issue 7): switching to another 640x480 frame within 150 ms (read, back-project, send),
refining the current frame within 300 ms. Runs on the bundled sample (or ``--sequence``): a
real viser server, a websocket client connected to it like a browser tab, and the app's own
callbacks. Frame switches are timed twice: "cold" (nothing cached) and "stepping" (the annotator
steps through frames, 0.3 s apart, and the neighbours are read ahead); "sent" is the time until
the point cloud's bytes have reached the connected client.

    .venv/bin/python benchmarks/bench_app.py [--sequence SEQ] [--switches 20] [--refines 10]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import viser  # noqa: E402

from annotate.app import App  # noqa: E402
from annotate.app_tracking import tracking_engine  # noqa: E402
from sequences.annotation import Annotation, FramePose, save_annotation  # noqa: E402
from sequences.reader import open_sequence  # noqa: E402


def sample_or_generated(work: Path) -> Path:
    """A copy of the bundled sample (its truth included), or a generated 640x480 sequence."""
    try:
        from sequences.sample import sample_sequence

        source = Path(sample_sequence())
    except Exception as error:  # the sample generator may not be there yet
        print(f"(bundled sample unavailable: {error}; using a generated sequence)")
        sys.path.insert(0, str(REPO / "tests"))
        from test_app_fixtures import make_sequence

        return make_sequence(work / "generated", frames=30)[0]
    target = work / source.name
    shutil.copytree(source, target, ignore=shutil.ignore_patterns("annotation.yaml*"))
    return target


def truth_document(root: Path, every: int = 10) -> Annotation | None:
    """A document with the true pose in every ``every``-th frame, from ``truth/truth.json`` when present."""
    path = root / "truth" / "truth.json"
    if not path.exists():
        return None
    truth = json.loads(path.read_text())
    ids = sorted(truth["poses"])
    doc = Annotation(root.name, truth.get("category", "other"), truth.get("symmetry", "none"), np.asarray(truth["extents"], dtype=float))
    for frame_id in ids[::every]:
        p = truth["poses"][frame_id]
        doc.frames[frame_id] = FramePose(np.asarray(p["position"], float), np.asarray(p["orientation"], float), "manual")
    return doc


class Listener:
    """A websocket client like a browser tab: records when each message arrives and its size."""

    def __init__(self, port: int) -> None:
        from websockets.sync.client import connect

        self.socket = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None)
        self.arrivals: list[tuple[float, int]] = []
        self.lock = threading.Lock()
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        try:
            for message in self.socket:
                with self.lock:
                    self.arrivals.append((time.perf_counter(), len(message)))
        except Exception:
            pass

    def wait_for_big_message(self, after: float, size: int, timeout: float = 5.0) -> float | None:
        deadline = time.perf_counter() + timeout
        while time.perf_counter() < deadline:
            with self.lock:
                for t, n in self.arrivals:
                    if t >= after and n >= size:
                        return t
            time.sleep(0.001)
        return None


def summary(values: list[float]) -> str:
    ms = np.asarray(values) * 1000
    return f"median {np.median(ms):6.1f} ms, p90 {np.percentile(ms, 90):6.1f} ms, max {ms.max():6.1f} ms (n={len(ms)})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequence", help="sequence folder (default: a copy of the bundled sample)")
    parser.add_argument("--switches", type=int, default=20)
    parser.add_argument("--refines", type=int, default=10)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_app_"))
    try:
        root = Path(args.sequence) if args.sequence else sample_or_generated(work)
        if not args.sequence:
            doc = truth_document(root)
            if doc is not None:
                save_annotation(doc, root / "annotation.yaml", backup=False)
        sequence = open_sequence(root)
        print(f"sequence {root} ({len(sequence)} frames, {sequence.camera.width}x{sequence.camera.height}); load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
        app = App(server, sequence)
        listener = Listener(server.get_port())
        time.sleep(1.0)
        cloud_bytes = int(len(app.cache.get(0).points) * 12 * 0.8)  # a message at least this big carries a point cloud
        n = len(sequence)

        cold, cold_sent, step, step_sent = [], [], [], []
        for k in range(args.switches):
            index = (7 * k + 3) % n  # jumps: nothing read ahead
            with app.cache._lock:
                app.cache._frames.clear()
            time.sleep(0.3)
            t0 = time.perf_counter()
            app.state.set_frame(index)
            t1 = time.perf_counter()
            arrived = listener.wait_for_big_message(t0, cloud_bytes)
            cold.append(t1 - t0)
            if arrived is not None:
                cold_sent.append(arrived - t0)
        app.state.set_frame(0)
        time.sleep(0.5)
        for k in range(min(args.switches, n - 1)):
            time.sleep(0.3)  # the annotator looks at the frame; the neighbours are read meanwhile
            t0 = time.perf_counter()
            app.state.step(1)
            t1 = time.perf_counter()
            arrived = listener.wait_for_big_message(t0, cloud_bytes)
            step.append(t1 - t0)
            if arrived is not None:
                step_sent.append(arrived - t0)
        print("switch frame, cold (read + back-project + draw):  " + summary(cold))
        if cold_sent:
            print("switch frame, cold, until bytes at the client:   " + summary(cold_sent))
        print("switch frame, stepping (neighbours read ahead):   " + summary(step))
        if step_sent:
            print("switch frame, stepping, until bytes at client:    " + summary(step_sent))

        if tracking_engine() is None:
            print("refine: tracking engine not installed")
        elif not app.state.annotation.frames:
            print("refine: no posed frames to refine against (no truth in this sequence)")
        else:
            rng = np.random.default_rng(0)
            times, before, after = [], [], []
            truth_path = root / "truth" / "truth.json"
            truth = json.loads(truth_path.read_text())["poses"] if truth_path.exists() else {}
            posed = set(app.state.annotation.frames)
            candidates = [i for i, f in enumerate(sequence.ids) if f not in posed]
            for index in candidates[: args.refines]:
                app.state.set_frame(index)
                pose, _ = app.state.pose()
                frame_id = sequence.ids[index]
                if frame_id in truth:  # start from the truth moved by about 3 mm (a hand-placed box)
                    pose.position = np.asarray(truth[frame_id]["position"], float)
                    pose.orientation = np.asarray(truth[frame_id]["orientation"], float)
                start = pose.position + rng.normal(0, 0.003, 3)
                app.commit_box(start, pose.orientation)
                app.tracking.last_refine_s = None
                app.tracking.refine_current()
                if app.tracking.last_refine_s is not None:
                    times.append(app.tracking.last_refine_s)
                    if frame_id in truth:
                        true_position = np.asarray(truth[frame_id]["position"], float)
                        before.append(np.linalg.norm(start - true_position))
                        after.append(np.linalg.norm(app.state.annotation.frames[frame_id].position - true_position))
            print("refine this frame (engine call):                  " + summary(times))
            if before:
                print(f"refine: box centre error {np.median(before) * 1000:.1f} mm -> {np.median(after) * 1000:.1f} mm (median of {len(after)})")
        print(f"load average now {os.getloadavg()[0]:.1f}")
        app.close()
        server.stop()
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
