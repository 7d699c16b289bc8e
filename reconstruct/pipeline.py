"""One sequence from posed frames to a mesh: carve, mesh, smooth, tight box (no files written).

Public entry point :func:`reconstruct_sequence` (the browser app and ``reconstruct-sequence``
call it); :func:`reconstruct.export.export_redwood` writes the result.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import trimesh

from sequences import timing
from sequences.annotation import Annotation, annotation_path
from sequences.errors import InputError
from sequences.reader import Sequence

from . import SURFACE, SURFACES, carving, evidence, meshing, support, tsdf  # noqa: F401 (SURFACE, SURFACES: defined there, light to import)
from .masks import render_masks
from .revolution import fit_revolution, revolved_fill
from .seen import SurfaceLabels, label_surface
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
    surface: SurfaceLabels | None = None  # what was seen: per-vertex labels, box faces bounded by a measurement
    rendered: "RenderedMasks | None" = field(default=None, repr=False, compare=False)  # the masks, when asked for

    def masks(self) -> dict[str, np.ndarray] | None:
        """Frame id -> (H, W) bool instance mask (reconstruct.masks) rendered with the reconstruction, or None when none
        were asked for or its mesh or poses were replaced since (then render them anew)."""
        if self.rendered is None or self.rendered.mesh is not self.mesh or self.rendered.poses is not self.poses:
            return None
        return self.rendered.masks


@dataclass(frozen=True)
class RenderedMasks:
    """Instance masks and the mesh and poses (the very objects) they were rendered from."""

    masks: dict[str, np.ndarray]
    mesh: trimesh.Trimesh
    poses: dict[str, np.ndarray]


#: Frames flagged for review (tracking's quality flags) are left out of the carving unless fewer than
#: this many unflagged frames, or this share of the posed ones, would remain: their poses may be
#: centimetres off and carve the object away. A frame flagged only for the spin its shape leaves free
#: (``flag_spin_only``: a mug's handle hidden) still carves: the rest of its pose is sound, and such
#: frames see the space a hand held through the grasps before.
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
    unknown = sorted(set(annotation.frames) - set(sequence.ids))
    if unknown:
        raise InputError(source, f"frame(s) {', '.join(unknown[:5])} of the annotation are not in the sequence {sequence.root}")
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


def _depth_frames(sequence: Sequence, ids: list[str], poses: dict[str, np.ndarray], ahead: bool = True) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
    """Depth images (metres) in order, decoded one ahead on a worker thread (PNG decoding overlaps carving; without
    ``ahead``, in turn on this thread). The pipeline passes over the frames up to three times (carving, fusion,
    labels): the sequence keeps the decoded images for the later passes (sequences.reader.DEPTH_CACHE_BYTES)."""
    scale = np.float32(sequence.camera.depth_scale)

    def decoded() -> Iterator[np.ndarray]:
        if not ahead:
            yield from (sequence.depth_raw(frame_id) for frame_id in ids)
            return
        with ThreadPoolExecutor(max_workers=1) as pool:
            pending = pool.submit(sequence.depth_raw, ids[0])
            for i in range(len(ids)):
                image = pending.result()
                if i + 1 < len(ids):
                    pending = pool.submit(sequence.depth_raw, ids[i + 1])
                yield image

    for frame_id, image in zip(ids, decoded()):
        yield frame_id, image.astype(np.float32) * scale, poses[frame_id]


#: Half voxel diagonals added to the free-space tolerance (carving.carve's ``voxel_margin``). The half diagonal keeps
#: a voxel whose centre lies in front of the measured surface but within reach of it; on a face seen head-on it
#: fattens the object by about that much: with none a laptop's screen seen edge-on loses its top, a whole one
#: fattens round rims and flat faces by millimetres.
VOXEL_MARGIN = 0.5


#: The annotated box bounds what no frame saw inside the object, grown by this share of its sides (a box placed a little small).
BOX_PRIOR_SLACK = 0.05
#: Nothing farther outside the annotated box than this share of its sides is object, measured or not: a hand that
#: held still, or a neighbour the object touches (a box on a block), is measured there in every frame and never seen
#: free. The suite's boxes are placed up to 8 % too small; the grid's margin (carving.default_margin) is wider still.
BOX_BOUND_SLACK = 0.10


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
    veto: float | None = carving.DEFAULT_VETO,
    settle: int = carving.DEFAULT_SETTLE,
    shadows: bool = carving.DEFAULT_SHADOWS,
    unbacked: int | None = carving.DEFAULT_UNBACKED,
    evidence_hull: bool | None = None,
    box_prior: bool = True,
    support_plane: bool = True,
    smoothing: str = "taubin",
    smoothing_iterations: int = 10,
    include_flagged: bool = False,
    surface: str = SURFACE,
    ahead: bool = True,
    masks: bool = False,
) -> Reconstruction:
    """Carve, mesh, smooth, fit the tight box of one annotated sequence and label what was seen.

    Poses every frame with a pose (or ``frames``), and carves with those not flagged for review
    (:func:`carving_frames`; all of them with ``include_flagged`` or explicit ``frames``);
    ``voxel_size`` and ``margin`` (per side, around the annotated box) in metres; ``k`` votes threshold
    (default :func:`carving.choose_k`). For ``symmetry: y`` the solid of revolution fills in what no frame
    observed where the measured surface is round (:mod:`reconstruct.revolution`). ``box_prior``: space no
    frame saw just behind a measured surface counts as object only inside the annotated box (grown by BOX_PRIOR_SLACK),
    and nothing beyond that box grown by BOX_BOUND_SLACK does. ``support_plane``: the
    plane a static object stands on, measured beside it in every frame, is not object (:mod:`reconstruct.support`). ``evidence_hull``
    (off by default, never for symmetry y): drop the unseen space no measured surface bounds
    (:mod:`reconstruct.evidence`). ``voxel_margin`` (half voxel diagonals in the free-space tolerance): None for
    VOXEL_MARGIN. ``surface`` (SURFACES): mesh the carved occupancy, or the fused depth where frames measured the
    surface and the carved hull elsewhere (:mod:`reconstruct.tsdf`). ``surface`` of the result labels the mesh
    observed, inferred or unseen (:mod:`reconstruct.seen`). ``ahead``: decode and prepare the next frame on a second
    thread while this one is carved (off: one thread, the same result; a batch's units, one per core, turn it off).
    ``masks``: render every posed frame's instance mask too (:func:`reconstruct.masks.render_masks`; with ``ahead``
    on a second thread while the labels are made; ``timings["masks"]`` is then the time they took beyond the labels').
    """
    source = str(annotation_path(sequence.root))
    if not (np.isfinite(voxel_size) and 0.0002 <= voxel_size <= 0.05):
        raise InputError(source, f"voxel size {voxel_size} m is outside 0.0002 .. 0.05 m")
    if surface not in SURFACES:
        raise ValueError(f"surface must be one of {SURFACES}, got {surface!r}")
    timings: dict[str, float] = {}
    posed = select_frames(sequence, annotation, frames, source)
    poses = {f: annotation.frames[f].matrix for f in posed}  # every selected frame gets its pose in the export
    # the document's poses are at the colour instants; each depth image is posed at its own (sequences.timing)
    at_depth = timing.at_depth_time(sequence, poses)
    ids = carving_frames(annotation, posed, include_flagged or frames is not None)  # a pose flagged for review may carve the object away
    say = progress or (lambda stage, done, total: None)

    start = time.perf_counter()
    grid = carving.make_grid(annotation.extents, voxel_size, margin)
    if grid.size > 60_000_000:
        raise InputError(source, f"voxel grid of {grid.shape} is too large: raise --voxel-size or check the extents")
    k_votes = carving.choose_k(len(ids)) if k is None else int(k)
    hull = veto is not None and bool(evidence_hull) and annotation.symmetry != "y"
    if voxel_margin is None:
        voxel_margin = VOXEL_MARGIN
    result = carving.carve(grid, _depth_frames(sequence, ids, at_depth, ahead), sequence.camera, k_votes, tol_sigmas, voxel_margin, silhouette_px, progress=lambda done: say("carve", done, len(ids)), veto=veto, settle=settle, shadows=shadows, unbacked=unbacked, ahead=ahead)
    timings["carve"] = time.perf_counter() - start

    start = time.perf_counter()
    occupied, behind = result.occupied, result.behind_count
    plane = None
    if support_plane:  # a table the object stands on is no part of it (a hand-held object finds none)
        plane = support.find_support(((T, depth) for _, depth, T in _depth_frames(sequence, ids[:: support.FRAME_STEP], at_depth, ahead)),
                                     sequence.camera, grid, annotation.extents)
    if plane is not None:
        cut = support.beyond_support(occupied, grid, plane)
        occupied = occupied & ~cut
        behind = None if behind is None else np.where(cut, 0, behind)
    timings["support"] = time.perf_counter() - start

    start = time.perf_counter()
    revolution, filled = None, None
    if annotation.symmetry == "y" and behind is not None:
        # the label is a prior: the solid of revolution fills in only what no frame observed, where the data is round
        # decided by the data: carved, or seen just behind a measured surface (a voxel seen free too few times to be
        # carved is not: its ring may carve it)
        observed = ~occupied | (behind > 0)
        revolution = fit_revolution(occupied & (behind > 0), grid)
        revolved = revolved_fill(occupied, observed, grid, revolution)
        filled, occupied = occupied & ~revolved, revolved
    elif annotation.symmetry == "y":
        occupied = carving.revolve_occupancy(occupied, grid, carved_share)
    elif behind is not None and hull:
        # symmetric objects fill their unseen sides from the rings instead (unbacked, those sides would go)
        occupied = evidence.evidence_hull(occupied, behind)
    if box_prior:
        # nothing beyond the box and its slack is object: a still hand or a touching neighbour is never seen free
        occupied = occupied & carving.inside_box(grid, annotation.extents * (1 + BOX_BOUND_SLACK))
        if behind is not None:
            # space no frame saw inside the object is object only inside the annotated box: the grid's margin (for
            # boxes placed too small) would otherwise stay solid wherever no frame looked, or looked too rarely to carve
            occupied = carving.bound_by_box(occupied, behind, grid, annotation.extents * (1 + BOX_PRIOR_SLACK))
    timings["symmetry"] = time.perf_counter() - start
    solid = meshing.largest_component(occupied)
    fused = None
    if surface == "tsdf":
        say("fuse", 0, len(ids))
        start = time.perf_counter()
        fused = tsdf.fuse(grid, _depth_frames(sequence, ids, at_depth, ahead), sequence.camera, solid)
        timings["fuse"] = time.perf_counter() - start
    say("mesh", 0, 1)
    start = time.perf_counter()
    try:
        if fused is None:
            mesh = meshing.occupancy_mesh(occupied, grid, smoothing, smoothing_iterations)
        else:
            mesh = meshing.field_mesh(tsdf.joined_field(solid, fused), grid, smoothing, smoothing_iterations)
    except ValueError as error:
        raise InputError(source, f"carving left no object ({error}); check the poses and extents") from error
    timings["mesh"] = time.perf_counter() - start

    start = time.perf_counter()
    mesh, new_poses, centre, extents = fit_tight_box(mesh, poses)
    timings["tight_box"] = time.perf_counter() - start
    start = time.perf_counter()
    render = partial(render_masks, mesh, new_poses, sequence.camera, sequence.depth)
    with ThreadPoolExecutor(max_workers=1) as pool:  # the masks render on a second core while the labels are made
        rendering = pool.submit(render) if masks and ahead else None
        # what was seen: the carving frames' depth once more, against the mesh at their poses
        labels = label_surface(mesh, grid, ((T, depth) for _, depth, T in _depth_frames(sequence, ids, at_depth, ahead)), sequence.camera, filled, centre, plane)
        timings["labels"] = time.perf_counter() - start
        start = time.perf_counter()
        if rendering is not None:
            frame_masks = rendering.result()
        else:
            frame_masks = render() if masks else None
    if masks:
        timings["masks"] = time.perf_counter() - start  # beyond the labels' time, when rendered beside them
    say("mesh", 1, 1)

    solid_voxels = int(solid.sum())
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
        "surface": surface,
        "annotated_extents": [float(x) for x in annotation.extents],
        "extents": [float(x) for x in extents],
        "centre_shift": [float(x) for x in centre],
        "mesh_vertices": int(len(mesh.vertices)),
        "mesh_faces": int(len(mesh.faces)),
        "watertight": meshing.is_watertight(mesh.faces),
        "volume": meshing.signed_volume(mesh),
        "timings": timings,
    }
    if revolution is not None:
        report["revolution"] = revolution.summary()
    if plane is not None:
        report["support_plane"] = plane.summary()
    if fused is not None:
        report["fused"] = {"frames": fused.frames, "truncation": fused.truncation, "voxels_measured": int((fused.weight >= tsdf.MIN_WEIGHT).sum())}
    report.update(labels.report())
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
        surface=labels,
        rendered=None if frame_masks is None else RenderedMasks(frame_masks, mesh, new_poses),
    )
