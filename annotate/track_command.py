"""``annotate SEQ --track``: refine the manual frames, give every frame a tracked pose, write the document."""

from __future__ import annotations

import sys
import time

import numpy as np

from sequences.annotation import annotation_path, load_checked, save_checked
from sequences.errors import InputError
from sequences.lock import DocumentLock
from sequences.reader import open_sequence


def run_track(args) -> int:
    """Headless tracking (``args.sequence``, ``args.annotation``); returns the exit code.

    Bad input (no sequence folder, a malformed or missing document, no manual frame) raises
    InputError, which the command line turns into a one-line error and exit code 2. The document is locked
    from its reading to its writing (a second writer is refused), and is not overwritten if another program
    changed it meanwhile.
    """
    sigma = getattr(args, "placement_sigma", None)
    if sigma is not None and (not all(np.isfinite(sigma)) or min(sigma) <= 0):
        raise InputError(None, f"--placement-sigma must be two positive numbers (deg, mm), got {sigma[0]:g} {sigma[1]:g}")
    root = args.sequence
    if root is None:
        from sequences.sample import sample_sequence

        root = sample_sequence()
    sequence = open_sequence(root)
    sequence.check()  # every frame decodes and the depth scale is plausible: before any work starts
    path = annotation_path(sequence.root, getattr(args, "annotation", None))
    with DocumentLock(path, "annotate --track"):  # one writer per document, from the read to the write
        return _track_locked(args, sequence, path, sigma)


def _track_locked(args, sequence, path, sigma) -> int:
    """Track and write the document, its lock held."""
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
    # a terminal redraws the bar in place; a log (a batch job) gets a line every few seconds, not every step
    interactive = sys.stderr.isatty()
    bar = tqdm(total=1, unit="step", desc=f"tracking {sequence.name}", file=sys.stderr, dynamic_ncols=True, mininterval=0.1 if interactive else 5.0)

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
    seconds = time.perf_counter() - start
    print(
        f"tracked {len(sequence)} frames of {sequence.name} in {seconds:.1f} s ({1000 * seconds / max(len(sequence), 1):.0f} ms/frame); "
        f"{len(flagged)} flagged for review; wrote {path}"
    )
    return 0


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
