"""A hinged object's centre along its hinge, from the ends of each frame's own points.

A laptop seen on its faces gives point-to-plane ICP nothing along its hinge (its x): the chains carry that
offset through whole stretches, and the model of all frames, built from them, is smeared along x by as much, so
neither the refinement nor the fitness of a wider crop (slide.py) can pull a stretch back: it can stay a
centimetre or more off along x, unflagged.

The box is tight, so its centre along x is halfway between the object's two ends along x, and a frame that sees
both ends shows them: the object-frame x of its points (those on the model's surfaces, so not the hand) runs
from one end to the other. Per frame, :func:`extent_along` gives that span and its middle. A frame whose span
falls short of the widest ones (the 75th percentile) has an end hidden (by the hand, or turned away) and its
middle is not used. Each frame is then moved along x by the median middle of the frames within +-``window`` that
saw both ends: single frames' middles scatter by 2-4 mm (the ends' sampling), and a stretch's offset is shared by
its frames. Frames move along x only: the rotations stay.

The window (``TrackingConfig.centring_window``) is +-1 frame: the chains' offset along x changes by several mm
from one frame to the next where a stretch slides, and a wider median mixes more of the neighbours' offsets into
a frame's; each frame's own middle alone fails more goal checks. The spans' ends are taken near the extremes
(``END_PERCENTILES``): at 2 / 98 the two ends' different densities shift the middle. The method has an error of
its own of a few mm over some stretches, which it adds where nothing slid: a hand's fingers at an end widen a
span, and even at the true poses of a laptop without a hand the middles lie about 1 mm off (the ends are sampled
unevenly).

A frame whose box slid further along x than the crop's slack (the crop margin, and what the placed box exceeds
the object by) sees its points run on to the crop's end, and the model, built from the frames about it, stops at
the object's end before that: its span is short, so it would take the offset of the frames about it, which do
not share its slide. Such an end is marked as cut (``Span.cut_low`` / ``cut_high``), and where the other end,
half the width of the frames that saw both ends in, puts the frame's middle more than ``MIN_SLIDE_M`` from the
offset of the frames about it, the frame takes that middle.

A frame that sees one of the object's end faces (square to the axis: a laptop's sides) measures that end on the face
itself (:func:`end_faces`), to a fraction of a millimetre where the spans' ends are off by 2-5 mm (the outline falls
short of the end, a face's noise runs beyond it), and takes the middle it gives, half the width of the frames that saw
both ends in. A laptop sees a face in a third to a half of its frames; there the spans' middles would take the
outline's shortfall for an offset. What is left: the width of the frames that saw both ends is their spans' (about
2 mm short of the object's: the outline's shortfall less the face's noise), so a face's frame lies half that off,
about 1 mm; the spans' ends at full resolution instead of voxels are no nearer. A frame measured costs ~6 ms of CPU
more (its crop at full resolution, the normals of the points near its ends).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import open3d as o3d

from evaluate.geometry import untransform

from .registration import ModelTarget
from .tracker import Tracker

#: the ends of a frame's span along the axis: percentiles of its points, so that a few stray points do not set them
END_PERCENTILES = (0.5, 99.5)
#: a frame's points count only within this many voxels of the model's surface (the hand holding the object is not)
ON_MODEL_VOXELS = 2.0
#: a span is measured only from at least this many points
MIN_SPAN_POINTS = 50
#: the widest spans: frames that saw both ends (a frame with an end hidden is shorter)
FULL_SPAN_PERCENTILE = 75.0
#: an end within this many voxels of the crop's own limit is the crop's, not the object's (a box slid along the axis)
CUT_VOXELS = 1.5
#: a frame whose one end is the crop's takes the middle its other end gives where that lies this far (m) from the
#: offset of the frames about it (a slide; nearer, the frames about it are the better measure)
MIN_SLIDE_M = 0.01
#: an end face: a frame's points (full resolution) whose normals lie within this of the axis, facing out
FACE_CONE_DEG = 30.0
#: ... searched among the points within this (m) inside the frame's span ends
FACE_BAND_M = 0.02
#: ... and counted only with at least this many points (a laptop's end seen edge-on gives a handful)
MIN_FACE_POINTS = 30
#: neighbours for a point's normal (the tracker's crops are voxel-downsampled to ~6 mm on a laptop, coarser than its
#: 12-20 mm thick ends: the faces' normals come from the frame's points at the image's resolution)
FACE_NORMAL_NEIGHBOURS = 16


class Span(NamedTuple):
    """A frame's points along the axis (m, object frame, from the box centre): their span, its middle and ends,
    whether each end is where the crop stops (the object runs on past it) rather than where the object ends, and where
    the end faces it sees lie."""

    width: float
    middle: float
    low: float = float("nan")
    high: float = float("nan")
    cut_low: bool = False
    cut_high: bool = False
    face_low: float = float("nan")  #: where the low end's face lies, seen (m); nan where not seen (end_faces)
    face_high: float = float("nan")  #: ... the high end's


def extent_along(tracker: Tracker, frame_id: str, pose: np.ndarray, target: ModelTarget, direction: np.ndarray) -> Span | None:
    """The span along ``direction`` (unit, object frame) of the frame's points that lie on ``target`` (object frame)
    at ``pose``; None where too few points lie on the model."""
    points, _ = tracker.crop(frame_id, pose)
    if len(points) < MIN_SPAN_POINTS:
        return None
    local = untransform(pose, points)
    direction = np.asarray(direction, dtype=np.float64)
    along = local @ direction
    distance, _ = target.nearest(local, ON_MODEL_VOXELS * tracker.config.voxel_size)
    on_model = np.isfinite(distance)
    if np.count_nonzero(on_model) < MIN_SPAN_POINTS:
        return None
    low, high = np.percentile(along[on_model], END_PERCENTILES)
    # the crop (the box grown by the margin, centred on the box centre) reaches this far along the direction; where
    # the frame's points run on to it, the object (or a hand on it) goes on past the crop, and the model (built
    # from the frames about it) may stop short of it: that end of the span is neither the object's nor measured
    reach = float(np.abs(direction) @ (tracker.box / 2 + tracker.config.crop_margin))
    edge = reach - CUT_VOXELS * tracker.config.voxel_size
    first, last = np.percentile(along, END_PERCENTILES)
    face_low, face_high = end_faces(tracker, frame_id, pose, direction, low, high)
    return Span(float(high - low), float(0.5 * (high + low)), float(low), float(high), bool(first <= -edge), bool(last >= edge),
                face_low, face_high)


def end_faces(tracker: Tracker, frame_id: str, pose: np.ndarray, direction: np.ndarray, low: float, high: float) -> tuple[float, float]:
    """Where the object's two end faces square to ``direction`` (unit, object frame) lie along it (m, from the box
    centre), measured on the frame's own points (full resolution) within ``FACE_BAND_M`` of its span's ends ``low``
    and ``high``: the median of those whose normals face out along the axis; nan for an end whose face the frame does
    not see (``MIN_FACE_POINTS``).

    A face seen gives its end to a fraction of a millimetre: its points lie on it. An end seen only as the outline
    of the faces beside it falls short (the last pixel before the background lies up to a pixel-step inside it, and
    depth jumps lose pixels), and a face's own end percentile lies beyond it (its noise).

    The points are not filtered by the model, as the spans are: a model of all frames keeps little of the end faces
    (seen by few frames, at offsets that differ by as much as they slid), and a frame would find few of its face
    points on it. A rotation error of the pose about the box centre moves the median by the angle times the face's
    distance from the centre across the axis (1 deg: 1.5 mm on a rendered laptop); a fit of the face's tilt, read
    at the box centre, would take that out, but does no better than the median and is not used.
    """
    points, _ = tracker.store.crop(frame_id, pose, tracker.box, tracker.config.crop_margin, None, keep=False)
    if len(points) < MIN_FACE_POINTS:
        return float("nan"), float("nan")
    along = untransform(pose, points) @ direction
    near = (along <= low + FACE_BAND_M) | (along >= high - FACE_BAND_M)
    if np.count_nonzero(near) < MIN_FACE_POINTS:
        return float("nan"), float("nan")
    points, along = points[near], along[near]
    outward = facing_normals(points) @ (pose[:3, :3] @ direction)
    cone = np.cos(np.deg2rad(FACE_CONE_DEG))
    faces = []
    for sign, end in ((-1.0, low), (1.0, high)):
        face = (sign * outward > cone) & (sign * (along - end) >= -FACE_BAND_M)
        faces.append(float(np.median(along[face])) if np.count_nonzero(face) >= MIN_FACE_POINTS else float("nan"))
    return faces[0], faces[1]


def facing_normals(points: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3; camera frame) of a frame's points ``points`` (N, 3; camera frame, m, not voxelled), from
    their ``FACE_NORMAL_NEIGHBOURS`` nearest points, each turned to face the camera (the surfaces a frame sees do)."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(FACE_NORMAL_NEIGHBOURS))
    cloud.orient_normals_towards_camera_location(np.zeros(3))
    return np.asarray(cloud.normals)


def centre_offsets(spans: list[Span | tuple[float, float] | None], tolerance: float, window: int) -> np.ndarray:
    """Per frame (in order): how far (m) the object's centre lies along the axis from the box centre, the median
    middle of the spans within +-``window`` frames that reach within ``tolerance`` (m) of the widest ones (the
    75th percentile of all spans). A frame without such a span about it shares its stretch's offset, interpolated
    between the nearest frames that have one on either side and held beyond the first and last (left alone, such
    frames stay off where their neighbours are corrected).
    A frame whose :class:`Span` has one end cut by the crop takes the middle its other end gives, where that lies
    more than ``MIN_SLIDE_M`` from this offset (a slid box). A frame that sees an end face takes the middle that face
    gives, half the width of the frames that saw both ends in (the mean of the two where it sees both). 0 everywhere
    where no frame has a span."""
    widths = np.array([s[0] if s is not None else np.nan for s in spans])
    middles = np.array([s[1] if s is not None else np.nan for s in spans])
    if not np.any(np.isfinite(widths)):
        return np.zeros(len(spans))
    full = np.nanpercentile(widths, FULL_SPAN_PERCENTILE)
    seen = np.where(np.isfinite(widths) & (widths >= full - tolerance), middles, np.nan)
    offsets = np.full(len(spans), np.nan)
    for i in range(len(spans)):
        near = seen[max(0, i - window) : i + window + 1]
        if np.any(np.isfinite(near)):
            offsets[i] = float(np.nanmedian(near))
    # never empty: the widest span is at least the 75th percentile, so its own frame has an offset
    measured = np.flatnonzero(np.isfinite(offsets))
    offsets = np.interp(np.arange(len(spans)), measured, offsets[measured])
    # a frame whose box slid along the axis: one end is cut by the crop, and the other end, half the object's width
    # in, gives its middle (the frames about it slid too, or saw both ends and do not share its offset)
    width = float(np.nanmedian(np.where(np.isfinite(seen), widths, np.nan)))
    for i, span in enumerate(spans):
        if not isinstance(span, Span):
            continue
        faced = [f + s * width / 2 for f, s in ((span.face_low, 1.0), (span.face_high, -1.0)) if np.isfinite(f)]
        if faced:  # an end face seen: the frame's own measure, to a fraction of a millimetre at its end
            offsets[i] = float(np.mean(faced))
            continue
        if np.isfinite(seen[i]) or span.cut_low == span.cut_high:
            continue
        own = span.high - width / 2 if span.cut_low else span.low + width / 2
        if abs(own - offsets[i]) > MIN_SLIDE_M:
            offsets[i] = own
    return offsets


def centred(pose: np.ndarray, offset: float, direction: np.ndarray) -> np.ndarray:
    """``pose`` (4x4, object -> camera) with its box centre moved by ``offset`` (m) along ``direction`` (unit, object
    frame)."""
    moved = np.array(pose, dtype=np.float64)
    moved[:3, 3] = moved[:3, 3] + offset * (moved[:3, :3] @ np.asarray(direction, dtype=np.float64))
    return moved
