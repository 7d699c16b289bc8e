"""``reconstruct-sequence SEQ...`` as a batch: one unit per sequence (see :mod:`batch`).

A unit reconstructs and exports its sequence on a worker. Every export renders and stages its files without
OUT's lock and swaps them in under it (:mod:`reconstruct.transaction`), so units export side by side and wait for
each other only for their renames; the client then puts ``annotations.json``'s entries in the order of the
command line (:func:`order_index`), as one run after another would have left them. BOP and NOCS number their
scenes: the client reserves the numbers in the order of the command line before the units start
(:func:`reserve`), so every worker count numbers the scenes alike. A unit reconstructs on one thread (no frame
decoded ahead on a second one, as a single SEQ does): the batch runs one unit per core.

Finished (:mod:`batch.units`): the marker ``OUT/.batch/<sequence>.json`` records the state of the unit's inputs
(the document's bytes, the frames' names, sizes and times, the camera file, the options) and OUT's index still
holds the sequence.
"""

from __future__ import annotations

import json
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from batch.units import file_bytes, listing, sha256_text
from sequences.annotation import Annotation, annotation_path, load_annotation
from sequences.errors import InputError
from sequences.reader import Sequence, open_sequence

from .export_index import FORMATS, read_index
from .transaction import ANNOTATIONS, OutLock, recover

#: Where a batch's finished markers live in OUT (a hidden folder: no format's reader looks at it).
MARKERS = ".batch"


def prepare(root: str | Path, annotation_file: str | None, fmt: str, ahead: bool = False) -> tuple[Sequence, Annotation, Path, bytes]:
    """Open and check a sequence and its document before any work: (sequence, annotation, document path, its bytes).
    ``ahead``: the frames decode on a second thread while the reconstruction's modules import."""
    sequence = open_sequence(root)
    # every frame decodes and the depth scale is plausible before any work starts; the carving reads the depth the
    # check decoded (Sequence keeps it)
    if ahead:
        with ThreadPoolExecutor(max_workers=1) as pool:
            checked = pool.submit(sequence.check)
            try:  # the slow imports (Open3D, trimesh, SciPy), made while the frames decode (the GIL let go)
                import open3d  # noqa: F401

                from . import export, pipeline  # noqa: F401
            except BaseException:
                checked.result()  # a bad frame is said first
                raise
            checked.result()
    else:
        sequence.check()
    path = annotation_path(root, annotation_file)
    data = file_bytes(path)
    annotation = load_annotation(path, default_sequence=sequence.name)
    if fmt == "nocs":  # before any work: NOCS's format holds its six categories only
        from .export_nocs import CLASS_IDS

        if annotation.category not in CLASS_IDS:
            raise InputError(path, f"category {annotation.category!r} has no NOCS class id (NOCS knows {', '.join(CLASS_IDS)})")
    return sequence, annotation, path, data or b""


def input_state(root: str | Path, options: dict, document: bytes) -> str:
    """The fingerprint of a unit's inputs: the options, the document's bytes, the frames and the camera file."""
    root = Path(root)
    return sha256_text("reconstruct-sequence", options, document, listing(root, ("rgb", "depth")), file_bytes(root / "camera.yaml") or b"")


def sequence_name(root: str | Path, annotation_file: str | None = None) -> str | None:
    """The name a sequence exports under (its document's, else its folder's); None when the document does not load."""
    try:
        return load_annotation(annotation_path(root, annotation_file), default_sequence=Path(root).resolve().name).sequence or Path(root).resolve().name
    except InputError:
        return None


def state_now(root: str | Path, annotation_file: str | None, out: str | Path, options: dict, name: str) -> str | None:
    """The state a finished unit's marker must record: None when OUT's index lacks the sequence."""
    try:
        index = read_index(Path(out))
    except InputError:
        return None
    if name not in index:
        return None
    return input_state(root, options, file_bytes(annotation_path(root, annotation_file)) or b"")


def marker_path(out: str | Path, name: str) -> Path:
    return Path(out) / MARKERS / f"{name}.json"


def _warnings(reconstruction) -> list[str]:
    """The reconstruction's warnings, a line each: the box's faces resting on surface no frame measured."""
    if reconstruction.surface is None:
        return []
    unmeasured = reconstruction.surface.unmeasured_faces()
    if not unmeasured:  # the box there rests on surface no frame measured: its extent is a guess
        return []
    faces = ", ".join(face for face, _ in unmeasured)
    return [f"{reconstruction.sequence}: the tight box's {faces} face{'s' if len(unmeasured) > 1 else ''} rest on surface "
            f"no frame measured; {unmeasured[0][1]}"]


def summary_of(reconstruction, path: Path, state: str) -> dict:
    return {"sequence": reconstruction.sequence, "frames": len(reconstruction.poses), "extents": [float(x) for x in reconstruction.extents],
            "index": str(path), "warnings": _warnings(reconstruction), "state": state}


def reconstruct(root: str | Path, options: dict, annotation_file: str | None = None, progress=None, ahead: bool = True):
    """Reconstruct one sequence (no files written): (reconstruction, sequence, annotation, input state). ``ahead``:
    decode the next frame on a second thread (:func:`reconstruct.pipeline.reconstruct_sequence`)."""
    sequence, annotation, _, document = prepare(root, annotation_file, options["format"], ahead)
    from .pipeline import reconstruct_sequence  # (imported by prepare while the frames were checked)

    reconstruction = reconstruct_sequence(sequence, annotation, options["voxel_size"], progress=progress, smoothing=options["smoothing"],
                                          include_flagged=options["include_flagged"], surface=options["surface"], ahead=ahead,
                                          masks=options["masks"] and options["format"] == "redwood75")  # (BOP and NOCS render their own)
    return reconstruction, sequence, annotation, input_state(root, options, document)


def export(reconstruction, sequence: Sequence, annotation: Annotation, out: Path, options: dict, progress=None, reserved: int | None = None) -> Path:
    """Export one reconstruction into ``out`` in ``options["format"]``; returns the index's path. ``reserved``: the
    scene number a batch reserved for it (BOP, NOCS)."""
    fmt = options["format"]
    if fmt == "bop":
        from .export_bop import export_bop

        return export_bop(reconstruction, sequence, out, masks=options["masks"], progress=progress, reserved=reserved)
    if fmt == "nocs":
        from .export_nocs import export_nocs

        return export_nocs(reconstruction, sequence, out, progress=progress, reserved=reserved)
    from .export import export_redwood

    return export_redwood(reconstruction, sequence, annotation, out, masks=options["masks"])


def reserve(out: str | Path, fmt: str, names: list[str]) -> dict[str, int]:
    """The scene numbers of a batch's sequences ``names`` (in the command line's order), for formats that number
    scenes; {} for REDWOOD75."""
    if fmt == "bop":
        from .export_bop import reserve_scene_ids

        return reserve_scene_ids(out, names)
    if fmt == "nocs":
        from .export_nocs import reserve_scene_numbers

        return reserve_scene_numbers(out, names)
    return {}


def whole_unit(root: str, annotation_file: str | None, out: str, options: dict, reserved: int | None = None) -> dict:
    """A unit on a worker: reconstruct and export one sequence; returns its summary. On one thread: a batch runs a
    unit per core, where a unit's second thread would only take turns with the other units."""
    reconstruction, sequence, annotation, state = reconstruct(root, options, annotation_file, ahead=False)
    path = export(reconstruction, sequence, annotation, Path(out), options, reserved=reserved)
    return summary_of(reconstruction, path, state)


def order_index(out: str | Path, before: list[str], names: list[str]) -> None:
    """Put ``OUT/annotations.json``'s entries in the order one run after another leaves them: those it held before
    the batch (``before``) where they were, then the batch's new sequences in the command line's order (``names``),
    then any another program added meanwhile. Rewritten atomically under OUT's lock, only when the order differs."""
    out = Path(out)
    path = out / ANNOTATIONS
    if not path.is_file():
        return
    from sequences.atomic import write_text_atomic

    with OutLock(out):
        recover(out)
        index = read_index(out)
        rank = {name: i for i, name in enumerate(before)}
        for name in names:
            rank.setdefault(name, len(rank))
        keys = list(index)
        ordered = sorted(keys, key=lambda k: rank.get(k, len(rank) + keys.index(k)))  # a few hundred keys at most
        if ordered != keys:
            write_text_atomic(path, json.dumps({k: index[k] for k in ordered}, indent=1))


def print_warnings(summary: dict) -> None:
    from tqdm import tqdm

    for line in summary.get("warnings", []):
        tqdm.write(f"warning: {line}", file=sys.stderr)


__all__ = ["FORMATS", "export", "marker_path", "order_index", "prepare", "reconstruct", "reserve", "sequence_name", "state_now", "whole_unit"]
