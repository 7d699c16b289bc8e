"""Kill every writer at random moments and check that what it writes is whole: the previous state or the new one.

    .venv/bin/python benchmarks/kill_writers.py [--kills 100] [--seed 0]

Writers: ``annotate SEQ --track`` (the annotation document), ``reconstruct-sequence`` (an export folder) and the
browser tool's saves (a session editing the document in a loop, as clicks do). Each is started on a small
synthetic sequence and SIGKILLed after a random delay within its run time; then the document must parse and be
the one before or one the writer would write, and the export folder (after the next run's recovery) must be the
previous export or the new one, file for file. Prints per writer the kills and the states found.
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from sequences.annotation import load_annotation  # noqa: E402
from sequences.errors import InputError  # noqa: E402

EDIT_LOOP = """
import sys, numpy as np
from annotate.app_state import AppState
from sequences.reader import open_sequence
state = AppState(open_sequence(sys.argv[1]))
print("ready", flush=True)
for k in range(100000):
    state.set_pose([0.001 * (k % 50), 0.0, 0.7], [0, 0, 0, 1])
"""


def export_state(out: Path) -> dict[str, bytes]:
    """An export folder's visible files, the reports' timings left out (they differ from run to run)."""
    state = {}
    for path in sorted(out.rglob("*")):
        rel = path.relative_to(out)
        if path.is_file() and not any(part.startswith(".") for part in rel.parts):
            data = path.read_bytes()
            if rel.parts[0] == "reports" and path.suffix == ".json":
                report = json.loads(data)
                report.pop("timings", None)
                data = json.dumps(report, sort_keys=True).encode()
            state[str(rel)] = data
    return state


def run(command: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", command[0], *command[1:]], cwd=REPO, capture_output=True, text=True, timeout=600)


def killed_after(command: list[str], delay: float, ready: bool = False) -> None:
    process = subprocess.Popen([sys.executable, "-c", command[0], *command[1:]], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    if ready:
        process.stdout.readline()
    time.sleep(delay)
    process.send_signal(signal.SIGKILL)
    process.wait()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kills", type=int, default=100, help="kills per writer")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    from sequences.synth import generate_sequence, load_truth, truth_annotation
    from sequences.annotation import save_annotation
    from reconstruct.transaction import OutLock, recover

    rng = np.random.default_rng(args.seed)
    work = Path(tempfile.mkdtemp(prefix="kills-"))
    root = generate_sequence(work / "can_0001", "can", frames=24, seed=3)
    truth = load_truth(root)
    placed = truth_annotation(truth, [truth.ids[2], truth.ids[12], truth.ids[21]], 2.0, 0.003, 0.05, seed=1)
    placed.sequence = "can_0001"
    document = root / "annotation.yaml"
    track = ["import sys; from annotate.cli import entry; sys.argv[0] = 'annotate'; entry()", str(root), "--track", "--workers", "1"]
    reconstruct = ["import sys; from reconstruct.cli import entry; sys.argv[0] = 'reconstruct-sequence'; entry()", str(root), "--out"]
    failures = 0

    # --track: the placed boxes, or the tracked document
    save_annotation(placed, document, backup=False)
    before = document.read_bytes()
    started = time.perf_counter()
    assert run(track).returncode == 0
    duration = time.perf_counter() - started
    tracked = document.read_bytes()
    found: Counter = Counter()
    for _ in range(args.kills):  # one process each
        document.write_bytes(before)
        killed_after(track, rng.uniform(0.3, duration))
        now = document.read_bytes()
        try:
            load_annotation(document)
        except InputError:
            found["unreadable"] += 1
            continue
        found["before" if now == before else "after" if now == tracked else "other"] += 1
    print(f"annotate --track ({duration:.1f} s a run): {dict(found)}", flush=True)
    failures += found["unreadable"] + found["other"]

    # reconstruct-sequence: the previous export or the new one, after the next run's recovery
    document.write_bytes(tracked)
    out = work / "out"
    previous = work / "previous"
    assert run(reconstruct + [str(previous)]).returncode == 0
    changed = load_annotation(document)
    changed.extents = changed.extents * 1.08
    save_annotation(changed, document, backup=False)
    new = work / "new"
    started = time.perf_counter()
    assert run(reconstruct + [str(new)]).returncode == 0
    duration = time.perf_counter() - started
    old_state, new_state = export_state(previous), export_state(new)
    found = Counter()
    for _ in range(args.kills):  # one process each
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(previous, out)
        killed_after(reconstruct + [str(out)], rng.uniform(0.3, duration))
        with OutLock(out):
            recover(out)
        state = export_state(out)
        found["previous" if state == old_state else "new" if state == new_state else "mixed"] += 1
    print(f"reconstruct-sequence ({duration:.1f} s a run): {dict(found)}", flush=True)
    failures += found["mixed"]

    # the browser tool's saves: a session editing in a loop, killed at random
    save_annotation(placed, document, backup=False)
    found = Counter()
    for _ in range(args.kills):  # one process each
        (root / "annotation.yaml.lock").unlink(missing_ok=True)
        killed_after([EDIT_LOOP, str(root)], rng.uniform(0.0, 1.0), ready=True)
        try:
            annotation = load_annotation(document)
            found["whole" if "0000001" in annotation.frames or annotation.frames else "empty"] += 1
        except InputError:
            found["unreadable"] += 1
    print(f"browser saves: {dict(found)}", flush=True)
    failures += found["unreadable"]
    print(f"broken states: {failures}")
    shutil.rmtree(work, ignore_errors=True)
    return 0 if failures == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
