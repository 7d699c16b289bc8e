"""NOCS export (``reconstruct-sequence --format nocs``): one sequence becomes one scene of NOCS's REAL275 layout.

Conventions are those of hughw19/NOCS_CVPR2019 (``dataset.py``: ``load_real_scenes``, ``process_data``;
``detect_eval.py``; ``utils.py``: ``draw_coord_mask``, ``align``, ``extract_bboxes``, ``load_mesh``) and of our
reader, :mod:`evaluate.datasets.nocs`:

- ``OUT/real_test/scene_<n>/<XXXX>_color.png`` (8-bit RGB), ``_depth.png`` (uint16 millimetres, 0 = none),
  ``_mask.png`` (uint8 instance ids: 1 = the object where it is visible, 255 = background),
  ``_coord.png`` (the NOCS map: per object pixel its normalised object coordinates, see below; 0 elsewhere) and
  ``_meta.txt`` (``1 <class id> <model name>``; class ids bottle 1, bowl 2, camera 3, can 4, laptop 5, mug 6).
  XXXX is the frame's position in the sequence (four digits), n counts scenes from 1.
- ``OUT/gts/real_test/results_real_test_scene_<n>_<XXXX>.pkl``: a results-style dict (detect_eval.py's keys):
  ``image_id`` (int), ``image_path`` (``real_test/scene_<n>/<XXXX>``), ``gt_class_ids`` (int64 (1,)),
  ``gt_bboxes`` (int32 (1, 4): y1, x1, y2, x2 of the mask, y2 and x2 exclusive), ``gt_RTs`` (float64 (1, 4, 4)),
  ``gt_scales`` (float32 (1, 3)), ``gt_handle_visibility`` and ``handle_visibility`` (int64 (1,): the key
  detect_eval.py reads from its gts pickles) -- 0 only for a mug whose handle no pixel shows.
- ``OUT/obj_models/real_test/<sequence>.obj`` (NOCS model axes, metres, centred on its box; ``v x y z`` and
  ``f a b c`` lines as ``utils.load_mesh`` splits them) and ``<sequence>.txt`` (the box's side lengths, metres).
- ``OUT/annotations.json``: our index (:mod:`reconstruct.export_index`): per sequence its scene, model, class id,
  the frame id of each image, and the frames left out.

NOCS's normalised object frame: model axes as NOCS's (ShapeNet x = NOCS z, y = y, z = -NOCS x:
``sequences.axes.SHAPENET_FROM_NOCS``), scaled so the box's diagonal is 1, centred on the box. ``gt_RTs``
folds that scale in: sRT maps NOCS coordinates (minus 0.5) to the camera (metres, OpenCV frame), with
s = |extents|. ``gt_scales`` are the box's sides over its diagonal (``process_data``: ``bbox / norm(bbox)``).
The NOCS map stores NOCS coordinates + 0.5 as 8-bit colour, red = x, green = y, blue = 1 - z
(``draw_coord_mask``'s left-handed map; ``process_data`` flips z back), rendered from the mesh.

REAL275's camera is fixed (NOCS's code and our reader assume its intrinsics,
``evaluate.datasets.nocs.NOCS_CAMERA``): frames from another camera are re-projected into it (same camera
centre and axes, so a pixel's depth is unchanged: depth nearest, colour bilinear), and masks and maps are
rendered in it. Frames whose object shows no pixel are left out (NOCS's loader asserts an instance has pixels).
The frames are rendered and staged before OUT's lock is taken; under it the scene gets its number and the
pickles that name it (:func:`reconstruct.export_index.export_unit`).
"""

from __future__ import annotations

import io
import pickle
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from evaluate.datasets.nocs import NOCS_CAMERA, NOCS_CATEGORIES
from sequences.axes import SHAPENET_FROM_NOCS
from sequences.camera import Camera
from sequences.errors import InputError
from sequences.names import check_name
from sequences.reader import Sequence

from .export_index import PENDING, export_unit, read_index, reserve_numbers, scene_number
from .masks import DEFAULT_TOLERANCE, MeshRenderer, visible_mask
from .pipeline import Reconstruction

#: REAL275's test split: our ground truth is test data.
SPLIT = "real_test"
#: NOCS class id of each category (NOCS's synset_names order).
CLASS_IDS = {name: class_id for class_id, name in NOCS_CATEGORIES.items()}
#: The one instance of a frame, and the mask's background (process_data asserts 255 is present).
INSTANCE, BACKGROUND = 1, 255
#: A mug's handle counts as visible where at least this many of its pixels show (NOCS then scores the mug as
#: asymmetric). The handle is where the object reaches further along -z (ShapeNet: the handle's side) than the
#: body, whose diameter is the x extent, plus HANDLE_MARGIN (m), which keeps a body slightly out of round from
#: counting as handle: a handle in view shows hundreds to thousands of pixels at REAL275's distances, one hidden
#: behind the body none.
HANDLE_MIN_PIXELS = 10
HANDLE_MARGIN = 0.003

#: progress(stage, done, total)
Progress = Callable[[str, int, int], None]


def nocs_pose(pose: np.ndarray, extents: np.ndarray) -> np.ndarray:
    """NOCS's 4x4 ``sRT`` of a pose (4x4, box-centred ShapeNet-axes object to camera, metres) of an object of
    ``extents`` (m): rotation R SHAPENET_FROM_NOCS times s = |extents|, the same translation."""
    sRT = np.eye(4)
    sRT[:3, :3] = float(np.linalg.norm(extents)) * (np.asarray(pose[:3, :3], dtype=np.float64) @ SHAPENET_FROM_NOCS)
    sRT[:3, 3] = pose[:3, 3]
    return sRT


def nocs_extents(extents: np.ndarray) -> np.ndarray:
    """(3,) box sides along NOCS's model axes of a box with ``extents`` along ShapeNet's (m)."""
    return np.abs(SHAPENET_FROM_NOCS.T @ np.asarray(extents, dtype=np.float64))


def object_points(rendered: np.ndarray, mask: np.ndarray, pose: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(object-frame points (N, 3), ShapeNet axes, metres; flat pixel indices (N,)) of the rendered surface
    (``rendered``: (H, W) depth, m) at the pixels of ``mask``: back-projected, then R^T (p - t)."""
    points, index = camera.backproject(rendered, mask)
    return (points - pose[:3, 3]) @ pose[:3, :3], index


def coord_image(points: np.ndarray, index: np.ndarray, extents: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) uint8 NOCS map: at the flat pixel ``index`` the normalised NOCS coordinates of the object points
    (ShapeNet axes, m) plus 0.5, red = x, green = y, blue = 1 - z, times 255; 0 elsewhere."""
    nocs = points @ SHAPENET_FROM_NOCS / np.linalg.norm(extents) + 0.5  # p_nocs = SHAPENET_FROM_NOCS^T p_sn
    nocs[:, 2] = 1.0 - nocs[:, 2]
    image = np.zeros((shape[0] * shape[1], 3), dtype=np.uint8)
    image[index] = np.clip(np.round(nocs * 255.0), 0, 255).astype(np.uint8)
    return image.reshape(shape[0], shape[1], 3)


def handle_visible(points: np.ndarray, extents: np.ndarray) -> bool:
    """Whether a mug's visible surface points (object frame, ShapeNet axes, m) show its handle (see HANDLE_MIN_PIXELS)."""
    body_back = extents[2] / 2 - extents[0] - HANDLE_MARGIN  # the body spans z in [z_max - diameter, z_max]
    return int((points[:, 2] < body_back).sum()) >= HANDLE_MIN_PIXELS


class Reprojection:
    """Frames of ``source`` seen through ``target`` (same centre and axes): each target pixel's ray meets the source
    image at (fx x + cx, fy y + cy); the mapping is computed once, then applied to every frame."""

    def __init__(self, source: Camera, target: Camera = NOCS_CAMERA) -> None:
        x = (np.arange(target.width) - target.cx) / target.fx
        y = (np.arange(target.height) - target.cy) / target.fy
        u = np.broadcast_to(source.fx * x[None, :] + source.cx, target.shape)
        v = np.broadcast_to(source.fy * y[:, None] + source.cy, target.shape)
        self.shape = target.shape
        # depth: the nearest source pixel (z is the same along the ray; 0 outside the source image)
        ui, vi = np.round(u).astype(np.int64), np.round(v).astype(np.int64)
        self.inside = (ui >= 0) & (ui < source.width) & (vi >= 0) & (vi < source.height)
        self.nearest = (vi * source.width + ui)[self.inside]
        # colour: bilinear between the four source pixels around (u, v); black outside
        u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
        fu, fv = u - u0, v - v0
        corners, weights = [], []
        for du, dv, w in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
            uu, vv = u0 + du, v0 + dv
            valid = (uu >= 0) & (uu < source.width) & (vv >= 0) & (vv < source.height)
            corners.append(np.where(valid, vv * source.width + uu, 0).reshape(-1))
            weights.append(np.where(valid, w, 0.0).reshape(-1, 1).astype(np.float32))
        self.corners, self.weights = corners, weights

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """(H', W') float32 target depth (m) of a source depth image (H, W), m."""
        out = np.zeros(self.shape, dtype=np.float32)
        out[self.inside] = depth.reshape(-1)[self.nearest]
        return out

    def color(self, color: np.ndarray) -> np.ndarray:
        """(H', W', 3) uint8 target colour of a source colour image (H, W, 3) uint8."""
        flat = color.reshape(-1, 3).astype(np.float32)
        out = sum(w * flat[c] for c, w in zip(self.corners, self.weights))
        return np.clip(np.round(out), 0, 255).astype(np.uint8).reshape(self.shape + (3,))


def reproject(color: np.ndarray, depth: np.ndarray, source: Camera, target: Camera = NOCS_CAMERA) -> tuple[np.ndarray, np.ndarray]:
    """Colour (H, W, 3) uint8 and depth (H, W) metres of ``source`` seen through ``target``: see :class:`Reprojection`."""
    reprojection = Reprojection(source, target)
    return reprojection.color(color), reprojection.depth(depth)


def frame_depth(sequence: Sequence, position: int, reprojection: Reprojection | None) -> np.ndarray:
    """(H, W) float32 depth (m) of a frame in REAL275's camera (``reprojection`` None: the sequence's own camera is it)."""
    depth = sequence.depth(position)
    return depth if reprojection is None else reprojection.depth(depth)


def frame_pngs(sequence: Sequence, position: int, depth: np.ndarray, reprojection: Reprojection | None) -> tuple[bytes, bytes]:
    """(colour PNG, depth PNG (uint16 mm)) of a frame in REAL275's camera: the sequence's own files, byte for byte,
    where they already are that (PNG colour; millimetre depth), else encoded from the (re-projected) images."""
    files = sequence.frames[position]
    if reprojection is None and files.color_path.suffix.lower() == ".png":
        color = files.color_path.read_bytes()
    else:
        image = sequence.color(position)
        color = png_bytes(image if reprojection is None else reprojection.color(image))
    if reprojection is None and sequence.camera.depth_scale == 0.001:
        return color, files.depth_path.read_bytes()
    millimetres = np.clip(np.round(depth.astype(np.float64) * 1000.0), 0, 65535).astype(np.uint16)
    return color, png_bytes(millimetres, DEPTH_PNG_LEVEL)


#: zlib level of the re-encoded depth PNGs: 1 encodes a noisy depth frame in less than half the time of PIL's
#: default 6, for a file a few per cent larger.
DEPTH_PNG_LEVEL = 1


def png_bytes(array: np.ndarray, level: int = 6) -> bytes:
    """PNG bytes of a uint8 (H, W) / (H, W, 3) or uint16 (H, W) image, zlib level ``level``."""
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG", compress_level=level)
    return buffer.getvalue()


class _PortablePickler(pickle.Pickler):
    """Pickles arrays as ``numpy.array(list, dtype)``: any NumPy (1.x as NOCS's code ran on, or 2.x) and our reader's
    NumPy-only unpickler load it; NumPy 2's own reduction names ``numpy._core``, which NumPy before 1.26 lacks."""

    def reducer_override(self, obj):
        if isinstance(obj, np.ndarray):
            return np.array, (obj.tolist(), obj.dtype.str)
        return NotImplemented


def results_pickle(image_id: int, image_path: str, class_id: int, bbox: np.ndarray, sRT: np.ndarray, extents: np.ndarray, handle: int) -> bytes:
    """The ground-truth pickle of one frame with one instance (see the module docstring for its fields)."""
    nocs = nocs_extents(extents)
    class_ids = np.array([class_id], dtype=np.int64)
    visibility = np.array([handle], dtype=np.int64)
    data = {
        "image_id": int(image_id),
        "image_path": image_path,
        "gt_class_ids": class_ids,
        "gt_bboxes": np.asarray(bbox, dtype=np.int32).reshape(1, 4),
        "gt_RTs": np.asarray(sRT, dtype=np.float64).reshape(1, 4, 4),
        "gt_scales": (nocs / np.linalg.norm(nocs)).astype(np.float32).reshape(1, 3),
        "gt_handle_visibility": visibility,
        "handle_visibility": visibility.copy(),
    }
    buffer = io.BytesIO()
    _PortablePickler(buffer, protocol=2).dump(data)
    return buffer.getvalue()


def mask_bbox(mask: np.ndarray) -> np.ndarray:
    """(4,) int32 y1, x1, y2, x2 of a non-empty mask, y2 and x2 exclusive (``utils.extract_bboxes``)."""
    ys, xs = np.nonzero(mask)
    return np.array([ys.min(), xs.min(), ys.max() + 1, xs.max() + 1], dtype=np.int32)


def obj_bytes(mesh: trimesh.Trimesh, name: str) -> bytes:
    """OBJ text of a ShapeNet-axes mesh (m) in NOCS's model axes: ``v x y z`` and ``f a b c`` lines, single spaces."""
    body = io.StringIO()
    body.write(f"# {name}: reconstruct-sequence (NOCS model axes, metres, centred on its box)\n")
    np.savetxt(body, np.asarray(mesh.vertices, dtype=np.float64) @ SHAPENET_FROM_NOCS, fmt="v %.9g %.9g %.9g")
    np.savetxt(body, np.asarray(mesh.faces) + 1, fmt="f %d %d %d")
    return body.getvalue().encode("ascii")


def extents_bytes(extents: np.ndarray) -> bytes:
    """``<model>.txt``: the box's sides along NOCS's model axes, metres, one a line (as REAL275's files)."""
    body = io.StringIO()
    np.savetxt(body, nocs_extents(extents))
    return body.getvalue().encode("ascii")


def export_nocs(reconstruction: Reconstruction, sequence: Sequence, out_dir: str | Path, progress: Progress | None = None,
                reserved: int | None = None) -> Path:
    """Write one reconstruction into ``out_dir`` as a REAL275-layout scene (see the module docstring); returns the
    index's path. ``reserved``: the number a batch reserved (used where the sequence has none yet and it is
    free). The frames are rendered and staged before OUT's lock is taken (:func:`reconstruct.export_index.export_unit`).
    A failure or a kill leaves ``out_dir``'s previous export whole."""
    out = Path(out_dir)
    name = check_name(reconstruction.sequence, "sequence name", out)
    category = reconstruction.category
    if category not in CLASS_IDS:
        raise InputError(sequence.root, f"category {category!r} has no NOCS class id (NOCS knows {', '.join(CLASS_IDS)})")
    class_id = CLASS_IDS[category]
    frame_ids = sorted(reconstruction.poses, key=sequence.index)
    if not frame_ids:
        raise InputError(sequence.root, "no posed frame to export")
    source, target = sequence.camera, NOCS_CAMERA
    same_camera = source.K.tolist() == target.K.tolist() and source.shape == target.shape  # else re-projected into REAL275's
    extents = np.asarray(reconstruction.extents, dtype=np.float64)

    pending = f"{SPLIT}/{PENDING}"  # the scene folder, numbered under the lock

    def prepare(stage) -> tuple[dict, list[str], dict]:
        """Every frame rendered and staged: (frames {stem: frame id}, frames left out, pickle fields per stem)."""
        renderer = MeshRenderer(reconstruction.mesh, target)
        reprojection = None if same_camera else Reprojection(source, target)
        frames, skipped, truths = {}, [], {}
        for done, frame_id in enumerate(frame_ids):  # frames in turn; pixels vectorised
            if progress is not None:
                progress("export", done, len(frame_ids))
            position = sequence.index(frame_id)
            stem = f"{position:04d}"
            pose = reconstruction.poses[frame_id]
            depth = frame_depth(sequence, position, reprojection)
            rendered = renderer.depth(pose)
            mask = visible_mask(rendered, depth, DEFAULT_TOLERANCE)
            if not mask.any():
                skipped.append(frame_id)
                continue
            points, pixels = object_points(rendered, mask, pose, target)
            handle = int(handle_visible(points, extents)) if category == "mug" else 1
            labels = np.full(target.shape, BACKGROUND, dtype=np.uint8)
            labels[mask] = INSTANCE
            color_png, depth_png = frame_pngs(sequence, position, depth, reprojection)
            stage(f"{pending}/{stem}_color.png", color_png)
            stage(f"{pending}/{stem}_depth.png", depth_png)
            stage(f"{pending}/{stem}_mask.png", png_bytes(labels))
            stage(f"{pending}/{stem}_coord.png", png_bytes(coord_image(points, pixels, extents, target.shape)))
            stage(f"{pending}/{stem}_meta.txt", f"{INSTANCE} {class_id} {name}\n".encode("ascii"))
            truths[stem] = (position, mask_bbox(mask), nocs_pose(pose, extents), handle)
            frames[stem] = frame_id
        if not frames:
            raise InputError(sequence.root, "the object shows no pixel in any posed frame (in REAL275's camera): nothing to export")
        stage(f"obj_models/{SPLIT}/{name}.obj", obj_bytes(reconstruction.mesh, name))
        stage(f"obj_models/{SPLIT}/{name}.txt", extents_bytes(extents))
        return frames, skipped, truths

    def finish(index: dict, transaction, prepared) -> tuple[dict, list[str], list[str]]:
        """Under OUT's lock: the scene's number, and the pickles that name it (a few hundred bytes each)."""
        frames, skipped, truths = prepared
        previous = index.get(name) if isinstance(index.get(name), dict) else {}
        taken = {int(p.name.removeprefix("scene_")) for p in (out / SPLIT).glob("scene_*") if p.name.removeprefix("scene_").isdigit()}
        number = scene_number(index, name, "scene_number", taken, reserved)
        scene = f"scene_{number}"
        folder = f"{SPLIT}/{scene}"
        transaction.rename(pending, folder)
        pickles = []
        for stem, (position, bbox, sRT, handle) in truths.items():
            pickle_name = f"gts/{SPLIT}/results_{SPLIT}_{scene}_{stem}.pkl"
            transaction.stage(pickle_name, results_pickle(position, f"{folder}/{stem}", class_id, bbox, sRT, extents, handle))
            pickles.append(pickle_name)
        obsolete = [p for p in previous.get("pickles", []) if isinstance(p, str) and p not in pickles]
        entry = {"split": SPLIT, "scene_number": number, "scene": scene, "model": name, "category": category, "class_id": class_id,
                 "symmetry": reconstruction.symmetry, "frames": frames, "skipped": skipped, "pickles": pickles,
                 "reprojected_from": None if same_camera else source.to_dict()}
        return entry, [folder], obsolete

    return export_unit(out, name, "nocs", prepare, finish)


def reserve_scene_numbers(out: str | Path, names: list[str]) -> dict[str, int]:
    """The scene numbers a batch's exports of ``names`` get, in this order (:func:`reconstruct.export_index.reserve_numbers`)."""
    out = Path(out)
    taken = {int(p.name.removeprefix("scene_")) for p in (out / SPLIT).glob("scene_*") if p.name.removeprefix("scene_").isdigit()}
    return reserve_numbers(read_index(out), names, "scene_number", taken)
