"""``annotate SEQ --track``: refine the manual frames, give every frame a tracked pose, write the document.

``annotate --track SEQ SEQ...`` (or any SEQ with ``--cluster``) is a batch (:mod:`batch`): one unit per
sequence, each tracked on one process (the poses are the same for any count: annotate.tracking.workers), N at
once on local processes or on a Dask cluster. A unit is finished when its marker ``<document>.tracked.json``
records the document as the unit wrote it, with the same engine and options; a rerun skips it, and tracks again
a document edited since (a box placed or moved).
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from sequences.annotation import annotation_path, load_checked, save_checked
from sequences.errors import EXIT_BAD_INPUT, InputError
from sequences.lock import DocumentLock
from sequences.reader import open_sequence


def run_track(args) -> int:
    """Headless tracking (``args.sequence``, ``args.annotation``); returns the exit code.

    Bad input (no sequence folder, a malformed or missing document, no manual frame) raises
    InputError, which the command line turns into a one-line error and exit code 2. The document is locked
    from its reading to its writing (a second writer is refused), and is not overwritten if another program
    changed it meanwhile.
    """
    print(track_line(track_one(args)))
    return 0


def track_line(summary: dict) -> str:
    """The line that says what a track did (:func:`track_one`'s summary)."""
    return (f"tracked {summary['frames']} frames of {summary['sequence']} in {summary['seconds']:.1f} s "
            f"({1000 * summary['seconds'] / max(summary['frames'], 1):.0f} ms/frame); {summary['flagged']} flagged for review; wrote {summary['document']}")


def _sigma(args):
    sigma = getattr(args, "placement_sigma", None)
    if sigma is not None and (not all(np.isfinite(sigma)) or min(sigma) <= 0):
        raise InputError(None, f"--placement-sigma must be two positive numbers (deg, mm), got {sigma[0]:g} {sigma[1]:g}")
    return sigma


def track_one(args, bar: bool = True) -> dict:
    """Track one sequence (``args.sequence``: None for the bundled sample) and write its document; returns the
    summary: sequence, frames, flagged, document, seconds, and the unit's state (a batch's marker records it)."""
    sigma = _sigma(args)
    root = args.sequence
    if root is None:
        from sequences.sample import sample_sequence

        root = sample_sequence()
    sequence = open_sequence(root)
    # every frame decodes and the depth scale is plausible before any work starts; the frames decode (the GIL let go)
    # while the engine's modules import, and the tracker reads the depth the check decoded (Sequence keeps it)
    with ThreadPoolExecutor(max_workers=1) as pool:
        checked = pool.submit(sequence.check)
        try:
            from .engines import engine_name, tracking_engine

            tracking_engine(engine_name(getattr(args, "engine", None)))
            problem = None
        except ValueError as error:  # an unknown engine ($REDWOOD_GT_ENGINE)
            problem = InputError(None, str(error))
        checked.result()  # a bad frame is said first
        if problem is not None:
            raise problem
    path = annotation_path(sequence.root, getattr(args, "annotation", None))
    with DocumentLock(path, "annotate --track"):  # one writer per document, from the read to the write
        return _track_locked(args, sequence, path, sigma, bar)


def _track_locked(args, sequence, path, sigma, show_bar: bool = True) -> dict:
    """Track and write the document, its lock held; returns the summary (see :func:`track_one`)."""
    from tqdm import tqdm

    from .engines import engine_name, tracking_engine

    annotation, read_as = load_checked(path, default_sequence=sequence.name)
    if not annotation.frames:
        raise InputError(path, "no frame has a box: place a box in two to four frames first (annotate SEQ)")
    unknown = sorted(set(annotation.frames) - set(sequence.ids))
    if unknown:
        raise InputError(path, f"frame {unknown[0]} is not in the sequence {sequence.root}")
    name = engine_name(getattr(args, "engine", None))
    track_sequence = tracking_engine(name).track_sequence
    config = _config(name, args, sigma)
    if getattr(args, "one_process", False):  # a batch's unit: the batch spreads the sequences over the cores
        config = _one_process(config)
    # a terminal redraws the bar in place; a log (a batch job) gets a line every few seconds, not every step
    interactive = sys.stderr.isatty()
    bar = tqdm(total=1, unit="step", desc=f"tracking {sequence.name}", file=sys.stderr, dynamic_ncols=True, mininterval=0.1 if interactive else 5.0,
               disable=not show_bar)

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(max(done - bar.n, 0))  # update, not refresh: tqdm then draws at most every mininterval

    start = time.perf_counter()
    try:
        tracked = track_sequence(sequence, annotation, config=config, progress=progress)
    except ValueError as error:
        raise InputError(path, str(error)) from error
    finally:
        bar.close()
    save_checked(tracked, path, read_as)
    flagged = [f for f, pose in tracked.frames.items() if pose.extra.get("flagged")]
    return {"sequence": sequence.name, "frames": len(sequence), "flagged": len(flagged), "document": str(path), "engine": name,
            "seconds": time.perf_counter() - start, "state": _state(path, _options(name, args, sigma))}


def _config(engine: str, args, sigma) -> object:
    """The engine's settings from the command line: the placement sigma (deg, mm), and the chains' own options."""
    if engine == "graph":
        from dataclasses import replace

        from .estimator import EstimatorConfig

        config = EstimatorConfig()
        return config if sigma is None else replace(config, anchor_sigma_deg=sigma[0], anchor_sigma_m=sigma[1] / 1000)
    from .tracking import TrackingConfig

    config = TrackingConfig()
    if sigma is not None:
        config.manual_rotation_sigma_deg, config.manual_translation_sigma = sigma[0], sigma[1] / 1000
    config.registration.facing = bool(getattr(args, "facing", True))
    if getattr(args, "workers", None) is not None:
        config.workers = int(args.workers)
    return config


# ------------------------------------------------------------------------------------------------ batches

def _one_process(config):
    """Either engine's settings with its independent work on this process (the poses are the same for any count)."""
    from dataclasses import replace

    return replace(config, workers=1) if hasattr(config, "workers") else config


def _options(engine: str, args, sigma) -> dict:
    """What, beside the document, makes a sequence's tracked poses (a unit's state records it)."""
    return {"engine": engine, "placement_sigma": None if sigma is None else [float(s) for s in sigma], "facing": bool(getattr(args, "facing", True))}


def _state(path: Path, options: dict) -> str | None:
    """The state of a tracked document: its bytes and the options (see batch.units)."""
    from batch.units import file_bytes, sha256_text

    data = file_bytes(path)
    return None if data is None else sha256_text("annotate --track", options, data)


def marker_path(document: Path) -> Path:
    return document.with_name(document.name + ".tracked.json")


def track_unit(root: str, annotation: str | None, options: dict) -> dict:
    """One sequence of a batch, on a worker: tracked on this process alone, no bar; returns the summary."""
    args = argparse.Namespace(sequence=root, annotation=annotation, engine=options["engine"], facing=options["facing"], workers=1,
                              placement_sigma=options["placement_sigma"], one_process=True)
    return track_one(args, bar=False)


def run_track_batch(args, stdout=None) -> tuple[int, dict]:
    """``annotate --track SEQ...``: one unit per sequence (see the module notes); returns (exit code, report)."""
    from batch import Unit, run_batch
    from batch.local import available_cores

    from .engines import TRACK_PRELOAD, engine_name

    sigma = _sigma(args)
    try:
        name = engine_name(getattr(args, "engine", None))  # here, not on the workers: their environment may differ
    except ValueError as error:
        raise InputError(None, str(error)) from error
    options = _options(name, args, sigma)
    units = []
    for root in args.sequences:
        document = annotation_path(root, args.annotation)
        units.append(Unit(root, track_unit, (root, args.annotation, options), marker_path(document), lambda document=document: _state(document, options)))

    def describe(outcome) -> str:
        return track_line({**outcome.summary, "seconds": outcome.seconds})

    workers = args.workers or available_cores()
    batch = run_batch(units, workers=workers, cluster=args.cluster, redo=args.redo, desc="track", noun="seq", preload=TRACK_PRELOAD, describe=describe)
    counts = batch.counts()
    print(f"{counts['done']} of {len(units)} sequence(s) tracked" + (f", {counts['skipped']} finished before" if counts["skipped"] else "")
          + (f", {counts['failed']} failed" if counts["failed"] else ""), file=sys.stderr)
    report = {"command": "annotate --track", "options": options, **batch.as_dict()}
    return (EXIT_BAD_INPUT if batch.failed else 0), report
