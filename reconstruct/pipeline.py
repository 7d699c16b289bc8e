"""One sequence from posed frames to a mesh: carve, mesh, smooth, tight box (no files written).

Public entry point :func:`reconstruct_sequence` (the browser app and ``reconstruct-sequence``
call it); :func:`reconstruct.export.export_redwood` writes the result.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import trimesh

from sequences.annotation import Annotation, annotation_path
from sequences.errors import InputError
from sequences.reader import Sequence

from . import carving, evidence, meshing
from .tight_box import fit_tight_box

#: progress(stage, done, total): called as frames are carved and at each stage.
Progress = Callable[[str, int, int], None]


@dataclass
class Reconstruction:
    """A reconstructed object.

    ``mesh``: object frame, ShapeNet axes, metres, centred on its tight box. ``extents``: full
    sides of that box (x, y, z). ``poses``: frame id -> 4x4 object-to-camera transform of the
    re-centred object. ``timings``: seconds per stage. ``report``: plain figures (JSON-able).
    """

    sequence: str
    category: str
    symmetry: str
    mesh: trimesh.Trimesh
    extents: np.ndarray
    poses: dict[str, np.ndarray]
    timings: dict[str, float]
    report: dict
    centre_shift: np.ndarray = field(default_factory=lambda: np.zeros(3))  # tight-box centre in the annotated object frame
    voxel_size: float = 0.002


#: Frames flagged for review (tracking's quality flags) are left out of the carving unless fewer than
#: this many unflagged frames, or this share of the posed ones, would remain. Measured on the v5 laptop,
#: seed 1 (78 of 100 frames flagged, their poses 10-16 mm off): the posed mesh's median F@5mm over all
#: its frames rose from 0.04 to 0.40 (bowl seed 1, 14 flagged: 0.89 -> 0.93); unchanged elsewhere.
#: A frame flagged only for the spin its shape leaves free (``flag_spin_only``: a mug's handle hidden) still
#: carves: the rest of its pose is sound, and such frames see the space a hand held through the grasps
#: before (measured: the report's mug, 3 boxes off by up to 5 deg, with them left out 10.8 cm tall, true 9.0).
MIN_CARVE_FRAMES = 10
MIN_CARVE_SHARE = 0.2


def carving_frames(annotation: Annotation, ids: list[str], include_flagged: bool = False) -> list[str]:
    """The frames of ``ids`` to carve with: those not flagged for review (or flagged for the spin only), unless too few are (see above)."""
    if include_flagged:
        return list(ids)
    unflagged = [f for f in ids if not annotation.frames[f].extra.get("flagged") or annotation.frames[f].extra.get("flag_spin_only")]
    if len(unflagged) < max(MIN_CARVE_FRAMES, MIN_CARVE_SHARE * len(ids)):
        return list(ids)
    return unflagged


def select_frames(sequence: Sequence, annotation: Annotation, frames: list[str] | None, source: str) -> list[str]:
    """Frame ids to pose: those of ``frames`` (or every frame with a pose) that the sequence holds (:func:`carving_frames` picks those that carve)."""
    if frames is None:
        chosen = [f for f in sequence.ids if f in annotation.frames]
    else:
        chosen = [str(f) for f in frames]
        missing = [f for f in chosen if f not in annotation.frames]
        if missing:
            raise InputError(source, f"frame(s) {', '.join(missing[:5])} have no pose in the annotation")
        known = set(sequence.ids)
        unknown = [f for f in chosen if f not in known]
        if unknown:
            raise InputError(sequence.root, f"frame(s) {', '.join(unknown[:5])} are not in the sequence")
    if not chosen:
        raise InputError(source, f"no frame of {sequence.root} has a pose: nothing to carve")
    return chosen


def _depth_frames(sequence: Sequence, ids: list[str], poses: dict[str, np.ndarray]) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
    """Depth images in order, decoded one ahead on a worker thread (PNG decoding overlaps carving)."""
    with ThreadPoolExecutor(max_workers=1) as pool:
        pending = pool.submit(sequence.depth, ids[0])
        for i, frame_id in enumerate(ids):
            depth = pending.result()
            if i + 1 < len(ids):
                pending = pool.submit(sequence.depth, ids[i + 1])
            yield frame_id, depth, poses[frame_id]


#: Half voxel diagonals added to the free-space tolerance (carving.carve's ``voxel_margin``): where carving
#: alone decides, for the rings of a symmetric object (symmetry y, with carving.OBSERVED_CARVED_SHARE), and
#: where the evidence hull (mugs) pools the voxels' decisions. The half diagonal keeps a voxel whose centre
#: lies in front of the measured surface but within reach of it; on a face seen head-on it fattens the
#: object by about that much. Measured (benchmarks/bench_reconstruct.py, v5, seeds 0-1 (rings and mugs
#: 0-3), worst extents error true / 1 deg + 2 mm poses): camera 1.0: +3.8 / +3.8 mm, 0.0: +2.5 / +2.1 mm;
#: laptop 1.0: +3.0 / +2.4, 0.0: +1.6 / -1.9; rings (ring share 0.5) with 0.0 lose a bowl's rim under
#: pose errors (seed 1 x -0.7 -> -3.8 mm); rings with 0.5 and ring share 0.6: bottles +2.9 / +2.0 mm,
#: bowls -1.3 / -1.4, cans +2.0 / +2.0 (1.0 and share 0.5: bottles +2.9 / +2.9, bowls -1.3 / -3.3);
#: the mug's evidence hull with 0.0 loses its inside (seed 2 F@1cm 0.991 -> 0.978).
PLAIN_VOXEL_MARGIN = 0.0
RING_VOXEL_MARGIN = 0.5
HULL_VOXEL_MARGIN = 1.0


def default_voxel_margin(symmetric: bool, hull: bool) -> float:
    """The free-space tolerance's half voxel diagonals: RING_VOXEL_MARGIN for a ``symmetric`` object (symmetry y),
    HULL_VOXEL_MARGIN where the evidence ``hull`` applies, else PLAIN_VOXEL_MARGIN."""
    return RING_VOXEL_MARGIN if symmetric else HULL_VOXEL_MARGIN if hull else PLAIN_VOXEL_MARGIN


def reconstruct_sequence(
    sequence: Sequence,
    annotation: Annotation,
    voxel_size: float = 0.002,
    frames: list[str] | None = None,
    progress: Progress | None = None,
    *,
    margin: float | None = None,
    k: int | None = None,
    tol_sigmas: float = carving.DEFAULT_TOL_SIGMAS,
    voxel_margin: float | None = None,
    silhouette_px: int = 0,
    carved_share: float = carving.DEFAULT_CARVED_SHARE,
    observed_share: bool = True,
    veto: float | None = carving.DEFAULT_VETO,
    settle: int = carving.DEFAULT_SETTLE,
    shadows: bool = carving.DEFAULT_SHADOWS,
    unbacked: int | None = carving.DEFAULT_UNBACKED,
    evidence_hull: bool | None = None,
    smoothing: str = "taubin",
    smoothing_iterations: int = 10,
    include_flagged: bool = False,
) -> Reconstruction:
    """Carve, mesh, smooth and fit the tight box of one annotated sequence.

    Poses every frame with a pose (or ``frames``), and carves with those not flagged for review
    (:func:`carving_frames`; all of them with ``include_flagged`` or explicit ``frames``);
    ``voxel_size`` and ``margin`` (per side, around
    the annotated box) in metres; ``k`` votes threshold (default :func:`carving.choose_k`).
    ``evidence_hull``: drop the unseen space no measured surface bounds (:mod:`reconstruct.evidence`;
    needs the veto's counts; never for symmetry y); None: for open containers (mugs) only.
    ``observed_share`` (symmetry y, with the veto's counts): a ring is carved when
    carving.OBSERVED_CARVED_SHARE of its observed voxels are, else when ``carved_share`` of all are.
    ``voxel_margin`` (half voxel diagonals in the free-space tolerance): None for
    :func:`default_voxel_margin`.
    """
    source = str(annotation_path(sequence.root))
    if not (np.isfinite(voxel_size) and 0.0002 <= voxel_size <= 0.05):
        raise InputError(source, f"voxel size {voxel_size} m is outside 0.0002 .. 0.05 m")
    timings: dict[str, float] = {}
    posed = select_frames(sequence, annotation, frames, source)
    poses = {f: annotation.frames[f].matrix for f in posed}  # every selected frame gets its pose in the export
    ids = carving_frames(annotation, posed, include_flagged or frames is not None)  # a pose flagged for review may carve the object away
    say = progress or (lambda stage, done, total: None)

    start = time.perf_counter()
    grid = carving.make_grid(annotation.extents, voxel_size, margin)
    if grid.size > 60_000_000:
        raise InputError(source, f"voxel grid of {grid.shape} is too large: raise --voxel-size or check the extents")
    k_votes = carving.choose_k(len(ids)) if k is None else int(k)
    hull = veto is not None and (evidence.applies(annotation.category, annotation.symmetry) if evidence_hull is None else evidence_hull)
    if voxel_margin is None:
        voxel_margin = default_voxel_margin(annotation.symmetry == "y", hull)
    result = carving.carve(grid, _depth_frames(sequence, ids, poses), sequence.camera, k_votes, tol_sigmas, voxel_margin, silhouette_px, progress=lambda done: say("carve", done, len(ids)), veto=veto, settle=settle, shadows=shadows, unbacked=unbacked)
    timings["carve"] = time.perf_counter() - start

    start = time.perf_counter()
    occupied = result.occupied
    if annotation.symmetry == "y":
        observed = None if result.behind_count is None or not observed_share else (result.free_count > 0) | (result.behind_count > 0)
        occupied = carving.revolve_occupancy(occupied, grid, carving.OBSERVED_CARVED_SHARE if observed is not None else carved_share, observed)
    elif result.behind_count is not None and hull:
        # symmetric objects fill their unseen sides from the rings instead (unbacked, those sides would go)
        occupied = evidence.evidence_hull(occupied, result.behind_count)
    timings["symmetry"] = time.perf_counter() - start
    say("mesh", 0, 1)
    start = time.perf_counter()
    try:
        mesh = meshing.occupancy_mesh(occupied, grid, smoothing, smoothing_iterations)
    except ValueError as error:
        raise InputError(source, f"carving left no object ({error}); check the poses and extents") from error
    timings["mesh"] = time.perf_counter() - start

    start = time.perf_counter()
    mesh, new_poses, centre, extents = fit_tight_box(mesh, poses)
    timings["tight_box"] = time.perf_counter() - start
    say("mesh", 1, 1)

    solid_voxels = int(meshing.largest_component(occupied).sum())
    carved = set(ids)
    report = {
        "sequence": annotation.sequence or sequence.name,
        "category": annotation.category,
        "symmetry": annotation.symmetry,
        "frames_used": len(ids),
        "frame_ids": ids,
        "frames_posed": len(posed),
        "flagged_left_out": [f for f in posed if f not in carved],
        "voxel_size": voxel_size,
        "grid_shape": list(grid.shape),
        "voxels": grid.size,
        "voxels_occupied": solid_voxels,
        "projections": result.projections,
        "k": k_votes,
        "annotated_extents": [float(x) for x in annotation.extents],
        "extents": [float(x) for x in extents],
        "centre_shift": [float(x) for x in centre],
        "mesh_vertices": int(len(mesh.vertices)),
        "mesh_faces": int(len(mesh.faces)),
        "watertight": bool(mesh.is_watertight),
        "volume": meshing.signed_volume(mesh),
        "timings": timings,
    }
    return Reconstruction(
        sequence=annotation.sequence or sequence.name,
        category=annotation.category,
        symmetry=annotation.symmetry,
        mesh=mesh,
        extents=extents,
        poses=new_poses,
        timings=timings,
        report=report,
        centre_shift=centre,
        voxel_size=voxel_size,
    )
