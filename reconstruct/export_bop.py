"""BOP export (``reconstruct-sequence --format bop``): one sequence becomes one BOP scene and one BOP object.

Written as bop_toolkit's ``docs/bop_datasets_format.md`` specifies it, and its scripts compute it
(``calc_gt_info.py``, ``calc_gt_masks.py``, ``calc_model_info.py``; ``inout.py``, ``misc.py``, ``visibility.py``):

- ``OUT/test/<scene id>/`` (six digits, from 1): ``rgb/<image id>.png|jpg`` and ``depth/<image id>.png`` (the
  sequence's own files, byte for byte; image id = the frame's position in the sequence, six digits),
  ``scene_camera.json`` (per image: ``cam_K`` 3x3 saved row-wise, pixels; ``depth_scale``: millimetres per depth
  unit), ``scene_gt.json`` (per image: ``[{obj_id, cam_R_m2c (3x3 saved row-wise), cam_t_m2c (mm)}]``, model to
  camera, OpenCV camera), ``scene_gt_info.json`` (per image and instance: ``bbox_obj``, ``bbox_visib`` as
  ``[x, y, width, height]`` with width = max x - min x as ``misc.calc_2d_bbox`` computes it, ``[-1, -1, -1, -1]``
  when nothing is visible; ``px_count_all`` (the whole silhouette, also outside the image), ``px_count_valid``,
  ``px_count_visib``, ``visib_fract`` = visib / all), ``mask/`` and ``mask_visib/<image id>_<gt index>.png``
  (uint8, 0 / 255). Visibility is BOP's ``bop19`` rule on distance images (not depth): a silhouette pixel is
  visible where the model's distance exceeds the measured one by at most :data:`DELTA_MM` (15 mm, the tolerance
  of BOP's datasets), or where there is no measurement.
- ``OUT/models/obj_<obj id>.ply`` (ASCII PLY with vertex normals, millimetres; the model frame is the document's:
  z up, origin at the centre of the model's box: ShapeNet axes turned by ``sequences.bop.SHAPENET_FROM_BOP``),
  ``OUT/models/models_info.json`` (per object: ``diameter`` = the largest distance between two vertices,
  ``min_x|y|z`` and ``size_x|y|z`` of the vertices' box, mm; a document's ``symmetry: y`` becomes
  ``symmetries_continuous: [{axis: [0, 0, 1], offset: [0, 0, 0]}]``, the y axis in BOP's z-up frame, through
  the origin). The scene's object id equals its scene id.
- ``OUT/test_targets_bop19.json``: the dataset's test targets as ``scripts/enumerate_test_targets.py`` lists them:
  per scene and image (ids ascending) ``{im_id, inst_count, obj_id, scene_id}`` for each object whose
  ``visib_fract`` is at least :data:`TARGET_MIN_VISIB` (0.1), ``inst_count`` its instances that visible (here 1).
- ``OUT/annotations.json``: our index (:mod:`reconstruct.export_index`): per sequence its scene and object ids,
  category, symmetry, and the frame id of each image id.

JSON files are laid out as ``inout.save_json`` writes them (a mapping: one line per image, keys in numeric order,
each value's keys sorted; a list: one item a line, its keys sorted). The frames are rendered and staged before
OUT's lock is taken; under it the scene gets its number and the files that hold it (``scene_gt.json``, the
model's name, ``models_info.json``, the targets), and the whole sequence is swapped in as one unit, the scene
folder whole.
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.distance import pdist

from sequences.bop import MM, SHAPENET_FROM_BOP
from sequences.camera import Camera
from sequences.documents import load_document
from sequences.errors import InputError
from sequences.names import check_name
from sequences.reader import Sequence

from .export_index import PENDING, export_unit, read_index, reserve_numbers, scene_number
from .masks import MeshRenderer, mask_png_bytes
from .pipeline import Reconstruction

#: Visibility tolerance (mm) of BOP's ``bop19`` rule: calc_gt_info.py's and calc_gt_masks.py's default ("5 mm for
#: ITODD, 15 mm for other datasets", says the format document). Depth noise of a PrimeSense-class sensor at 1 m
#: is a few mm, so 15 mm keeps the object's own noisy surface visible while a hand 2 cm in front occludes it.
DELTA_MM = 15.0
#: The split the scenes go to: our ground truth is test data.
SPLIT = "test"
#: The canvas on which the whole silhouette is rendered is this many images wide and high, the image in its
#: middle (calc_gt_info.py renders on 3x the image to count ``px_count_all`` beyond the image's border).
CANVAS = 3

#: The dataset's list of test targets (enumerate_test_targets.py's file name), in OUT beside models/.
TARGETS = "test_targets_bop19.json"
#: The least visible fraction of a target: enumerate_test_targets.py's ``min_visib_fract`` (BOP's targets since 2019).
TARGET_MIN_VISIB = 0.1

#: progress(stage, done, total)
Progress = Callable[[str, int, int], None]


def bop_json(content: dict) -> bytes:
    """JSON text as ``bop_toolkit_lib.inout.save_json`` writes a mapping: one ``"key": value`` line per item, keys in
    their (numeric) order, each value dumped with sorted keys."""
    items = sorted(content.items(), key=lambda item: int(item[0]) if str(item[0]).isdigit() else str(item[0]))
    lines = [f'  "{key}": {json.dumps(value, sort_keys=True)}' for key, value in items]
    return ("{\n" + ",\n".join(lines) + ("\n" if lines else "") + "}").encode("utf-8")


def distance_image(depth_mm: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W) float64 distance from the camera centre (mm) of a depth image (H, W) in mm (0 = none): depth times
    the length of the pixel's ray with z = 1, as ``misc.depth_im_to_dist_im_fast``."""
    depth = np.asarray(depth_mm, dtype=np.float64)
    h, w = depth.shape
    x = (np.arange(w) - K[0, 2]) / K[0, 0]
    y = (np.arange(h) - K[1, 2]) / K[1, 1]
    return depth * np.sqrt(1.0 + x[None, :] ** 2 + y[:, None] ** 2)


def visible_mask(dist_test: np.ndarray, dist_model: np.ndarray, delta: float = DELTA_MM) -> np.ndarray:
    """(H, W) bool: BOP's ``bop19`` visibility (``visibility._estimate_visib_mask``): model pixels whose distance
    exceeds the measured distance by at most ``delta`` (mm), or with no measurement (distance 0)."""
    d_diff = dist_model.astype(np.float32) - dist_test.astype(np.float32)
    return ((d_diff <= delta) | (dist_test == 0)) & (dist_model > 0)


def bbox_xywh(mask: np.ndarray, offset: tuple[int, int] = (0, 0)) -> list[int]:
    """``[x, y, width, height]`` (pixels) of a mask's pixels as ``misc.calc_2d_bbox`` (unclipped) gives it: width =
    max x - min x; ``offset`` (x, y) is subtracted (the image's corner on a larger canvas)."""
    ys, xs = np.nonzero(mask)
    x0, y0 = int(xs.min()) - offset[0], int(ys.min()) - offset[1]
    return [x0, y0, int(xs.max() - xs.min()), int(ys.max() - ys.min())]


def gt_info(depth_mm: np.ndarray, measured_mm: np.ndarray, K: np.ndarray, whole: np.ndarray | None = None, offset: tuple[int, int] = (0, 0),
            delta: float = DELTA_MM) -> tuple[dict, np.ndarray, np.ndarray]:
    """One instance's ``scene_gt_info.json`` entry and its two masks, as calc_gt_info.py and calc_gt_masks.py compute them.

    ``depth_mm``: (H, W) rendered depth (mm, 0 = missed) of the model in the image; ``measured_mm``: (H, W) the
    image's depth (mm, 0 = none); ``K``: the image's 3x3; ``whole``: the model's whole silhouette (bool) on a larger
    canvas whose pixel ``offset`` (x, y) is the image's (0, 0), or None where it lies inside the image.
    Returns (entry, mask (H, W) bool: the silhouette inside the image, mask_visib (H, W) bool).
    """
    dist_gt = distance_image(depth_mm, K)
    dist_im = distance_image(measured_mm, K)
    visib = visible_mask(dist_im, dist_gt, delta)
    mask = dist_gt > 0
    if whole is None:
        whole = mask
    px_all, px_visib = int(whole.sum()), int(visib.sum())
    entry = {
        "px_count_all": px_all,
        "px_count_valid": int((dist_im[mask] > 0).sum()),
        "px_count_visib": px_visib,
        "visib_fract": float(px_visib / px_all) if px_all > 0 else 0.0,
        # calc_gt_info.py fills both boxes only where something is visible
        "bbox_obj": bbox_xywh(whole, offset) if px_visib > 0 else [-1, -1, -1, -1],
        "bbox_visib": bbox_xywh(visib) if px_visib > 0 else [-1, -1, -1, -1],
    }
    return entry, mask, visib


class SilhouetteRenderer:
    """Depth (mm) of a mesh (object frame, m) posed in a camera's image, with its whole silhouette where part of it
    falls outside the image: then rendered on the CANVAS-times larger image around it (as calc_gt_info.py does).
    The silhouette lies inside the hull of the projected vertices, so where every vertex is in front of the camera
    and projects within (-1, W) x (-1, H), no pixel centre outside the image can see the mesh: the image alone is
    rendered (the canvas's prefix sums cost 65 ms a frame at 640x480)."""

    def __init__(self, mesh: trimesh.Trimesh, camera: Camera) -> None:
        self.camera = camera
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self.image = MeshRenderer(mesh, camera)
        self.canvas = MeshRenderer(mesh, canvas_camera(camera))

    def __call__(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, tuple[int, int]]:
        """(depth (H, W) mm in the image, whole silhouette on the canvas or None when inside the image, the image's
        corner on the canvas (x, y))."""
        cam = self.camera
        uv, z = cam.project(self.vertices @ pose[:3, :3].T + pose[:3, 3])
        if (z > 0).all() and uv[:, 0].min() > -1 and uv[:, 0].max() < cam.width and uv[:, 1].min() > -1 and uv[:, 1].max() < cam.height:
            return self.image.depth(pose).astype(np.float64) * MM, None, (0, 0)
        canvas = self.canvas.depth(pose).astype(np.float64) * MM
        x, y = (CANVAS // 2) * cam.width, (CANVAS // 2) * cam.height
        return canvas[y : y + cam.height, x : x + cam.width], canvas > 0, (x, y)


def diameter(points: np.ndarray) -> float:
    """The largest distance between two of the (N, 3) points (``misc.calc_pts_diameter``), exactly: the farthest
    pair lies on the convex hull, so only its vertices are compared."""
    points = np.asarray(points, dtype=np.float64)
    try:
        points = points[ConvexHull(points).vertices]
    except (QhullError, ValueError):  # flat or tiny point sets: compare them all
        pass
    return float(pdist(points).max()) if len(points) > 1 else 0.0


def model_info(vertices_mm: np.ndarray, symmetry: str) -> dict:
    """A ``models_info.json`` entry of a model (vertices (N, 3) in mm, BOP model frame): its diameter, the min
    corner and sizes of its vertices' box (``misc.calc_3d_bbox``), and the symmetry of the document."""
    lo, hi = vertices_mm.min(axis=0), vertices_mm.max(axis=0)
    info = {"diameter": diameter(vertices_mm)}
    info.update({f"min_{a}": float(v) for a, v in zip("xyz", lo)})
    info.update({f"size_{a}": float(v) for a, v in zip("xyz", hi - lo)})
    if symmetry == "y":  # continuous symmetry about the object's y axis, through the box centre (the origin)
        axis = SHAPENET_FROM_BOP.T @ np.array([0.0, 1.0, 0.0])
        info["symmetries_continuous"] = [{"axis": [int(round(a)) for a in axis], "offset": [0, 0, 0]}]
    return info


def ply_bytes(vertices_mm: np.ndarray, faces: np.ndarray, name: str) -> bytes:
    """ASCII PLY of a triangle mesh (vertices in mm) with angle-weighted vertex normals, as BOP's models are given;
    ``inout.load_ply`` reads it (``float`` vertex properties, ``list uchar int vertex_indices`` faces)."""
    mesh = trimesh.Trimesh(vertices_mm, faces, process=False)
    normals = trimesh.geometry.weighted_vertex_normals(len(vertices_mm), mesh.faces, mesh.face_normals, mesh.face_angles)
    header = "\n".join([
        "ply", "format ascii 1.0", f"comment {name}: reconstruct-sequence (BOP model: millimetres, z up, origin at the box centre)",
        f"element vertex {len(vertices_mm)}", *[f"property float {p}" for p in ("x", "y", "z", "nx", "ny", "nz")],
        f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header",
    ])
    body = io.StringIO()
    np.savetxt(body, np.hstack([vertices_mm, normals]), fmt="%.9g")
    np.savetxt(body, np.hstack([np.full((len(faces), 1), 3), faces]), fmt="%d")
    return (header + "\n" + body.getvalue()).encode("ascii")


def bop_pose(pose: np.ndarray) -> tuple[list[float], list[float]]:
    """(``cam_R_m2c`` row-wise 9 values, ``cam_t_m2c`` mm) of a 4x4 pose of the box-centred ShapeNet-axes object
    (metres): p_cam = R p_sn + t = (R SHAPENET_FROM_BOP) p_bop + t."""
    R = np.asarray(pose[:3, :3], dtype=np.float64) @ SHAPENET_FROM_BOP
    return [float(v) for v in R.reshape(-1)], [float(v) for v in np.asarray(pose[:3, 3], dtype=np.float64) * MM]


def canvas_camera(camera: Camera) -> Camera:
    """The camera of the CANVAS-times larger image whose middle is ``camera``'s image (same rays there)."""
    w, h = camera.width, camera.height
    return Camera(camera.fx, camera.fy, camera.cx + (CANVAS // 2) * w, camera.cy + (CANVAS // 2) * h, CANVAS * w, CANVAS * h, camera.depth_scale)


def _taken(out: Path) -> set[int]:
    """Scene ids on disk and object ids in models_info.json that the index does not account for (other BOP data)."""
    taken = {int(p.name) for p in (out / SPLIT).iterdir() if p.name.isdigit()} if (out / SPLIT).is_dir() else set()
    info = out / "models" / "models_info.json"
    if info.is_file():
        taken |= {int(k) for k in _existing_models_info(info) if str(k).isdigit()}
    return taken


def _existing_models_info(path: Path) -> dict:
    data = load_document(path, "models_info.json", as_yaml=False)
    if not isinstance(data, dict):
        raise InputError(path, "existing models_info.json is not a mapping of object ids; not overwriting it")
    return data


def targets_bop19(infos: dict, obj_id: int, scene_id: int, min_visib_fract: float = TARGET_MIN_VISIB) -> list[dict]:
    """``test_targets_bop19.json``'s entries of one scene with one object (enumerate_test_targets.py): per image
    (ids ascending) ``{im_id, inst_count, obj_id, scene_id}`` where the object's ``visib_fract`` is at least
    ``min_visib_fract``; ``infos``: ``scene_gt_info.json``'s content {im_id: [entry]}."""
    return [{"im_id": int(im_id), "inst_count": 1, "obj_id": int(obj_id), "scene_id": int(scene_id)}
            for im_id, entries in sorted(infos.items(), key=lambda item: int(item[0])) if entries[0]["visib_fract"] >= min_visib_fract]


def bop_json_list(content: list[dict]) -> bytes:
    """JSON text as ``bop_toolkit_lib.inout.save_json`` writes a list: one item a line, its keys sorted."""
    lines = [f"  {json.dumps(item, sort_keys=True)}" for item in content]
    return ("[\n" + ",\n".join(lines) + ("\n" if lines else "") + "]").encode("utf-8")


def _existing_targets(path: Path) -> list[dict]:
    data = load_document(path, TARGETS, as_yaml=False)
    if not isinstance(data, list) or not all(isinstance(t, dict) and isinstance(t.get("scene_id"), int) and isinstance(t.get("im_id"), int) for t in data):
        raise InputError(path, f"existing {TARGETS} is not a list of {{scene_id, im_id, ...}} targets; not overwriting it")
    return data


def merged_targets(existing: list[dict], scene: list[dict], scene_id: int) -> list[dict]:
    """The dataset's targets with scene ``scene_id``'s replaced by ``scene``, ordered by scene and image id (as
    enumerate_test_targets.py lists them); the order of the other scenes' own entries is kept within an image."""
    kept = [t for t in existing if t["scene_id"] != scene_id] + scene
    return sorted(kept, key=lambda t: (t["scene_id"], t["im_id"]))  # stable: several objects of an image keep their order


def export_bop(reconstruction: Reconstruction, sequence: Sequence, out_dir: str | Path, masks: bool = True, progress: Progress | None = None,
               reserved: int | None = None) -> Path:
    """Write one reconstruction into ``out_dir`` as a BOP scene and object (see the module docstring); returns the
    index's path. ``masks=False`` leaves out ``mask/`` and ``mask_visib/`` (optional in BOP); the rest is computed
    alike. ``reserved``: the scene id a batch reserved (used where the sequence has none yet and it is free). The
    frames are rendered and staged before OUT's lock is taken (:func:`reconstruct.export_index.export_unit`). A
    failure or a kill leaves ``out_dir``'s previous export whole."""
    out = Path(out_dir)
    name = check_name(reconstruction.sequence, "sequence name", out)
    camera = sequence.camera
    frame_ids = sorted(reconstruction.poses, key=sequence.index)
    if not frame_ids:
        raise InputError(sequence.root, "no posed frame to export")
    for frame_id in frame_ids:  # BOP names images by number: these are its files
        files = sequence.frames[sequence.index(frame_id)]
        if files.depth_path.suffix.lower() != ".png":
            raise InputError(files.depth_path, "BOP's depth images are PNG files")
    K = [float(v) for v in camera.K.reshape(-1)]
    depth_scale = float(camera.depth_scale * MM)  # BOP: multiply the depth image by this to get millimetres
    scene = f"{SPLIT}/{PENDING}"  # numbered under the lock
    model = f"models/{PENDING}.ply"

    def prepare(stage) -> tuple[dict, dict, dict, dict]:
        """Every frame rendered and staged: (poses {im_id: (R, t)}, gt infos, images {im_id: frame id}, model info)."""
        render = SilhouetteRenderer(reconstruction.mesh, camera)
        cameras, poses, infos, images = {}, {}, {}, {}
        for done, frame_id in enumerate(frame_ids):  # frames in turn; pixels vectorised
            if progress is not None:
                progress("export", done, len(frame_ids))
            im_id = sequence.index(frame_id)
            files = sequence.frames[im_id]
            suffix = ".jpg" if files.color_path.suffix.lower() in (".jpg", ".jpeg") else ".png"
            stage(f"{scene}/rgb/{im_id:06d}{suffix}", files.color_path.read_bytes())
            stage(f"{scene}/depth/{im_id:06d}.png", files.depth_path.read_bytes())
            pose = reconstruction.poses[frame_id]
            poses[im_id] = bop_pose(pose)
            measured = sequence.depth_raw(im_id).astype(np.float64) * depth_scale
            depth_mm, whole, offset = render(pose)
            info, mask, visib = gt_info(depth_mm, measured, camera.K, whole, offset)
            cameras[im_id] = {"cam_K": K, "depth_scale": depth_scale}
            infos[im_id] = [info]
            images[str(im_id)] = frame_id
            if masks:
                stage(f"{scene}/mask/{im_id:06d}_000000.png", mask_png_bytes(mask))
                stage(f"{scene}/mask_visib/{im_id:06d}_000000.png", mask_png_bytes(visib))
        stage(f"{scene}/scene_camera.json", bop_json(cameras))
        stage(f"{scene}/scene_gt_info.json", bop_json(infos))
        vertices_mm = np.asarray(reconstruction.mesh.vertices, dtype=np.float64) @ SHAPENET_FROM_BOP * MM  # p_bop = S^T p_sn
        stage(model, ply_bytes(vertices_mm, np.asarray(reconstruction.mesh.faces), name))
        return poses, infos, images, model_info(vertices_mm, reconstruction.symmetry)

    def finish(index: dict, transaction, prepared) -> tuple[dict, list[str], list[str]]:
        """Under OUT's lock: the scene's number, the files that hold it, the shared models_info.json and targets."""
        poses, infos, images, info = prepared
        number = scene_number(index, name, "scene_id", _taken(out), reserved)
        obj_id = number  # one object per scene
        folder = f"{SPLIT}/{number:06d}"
        transaction.rename(scene, folder)
        transaction.rename(model, f"models/obj_{obj_id:06d}.ply")
        gts = {im_id: [{"cam_R_m2c": R, "cam_t_m2c": t, "obj_id": obj_id}] for im_id, (R, t) in poses.items()}
        transaction.stage(f"{folder}/scene_gt.json", bop_json(gts))
        info_path = out / "models" / "models_info.json"
        models_info = _existing_models_info(info_path) if info_path.is_file() else {}
        models_info[str(obj_id)] = info
        transaction.stage("models/models_info.json", bop_json(models_info))
        targets_path = out / TARGETS
        existing = _existing_targets(targets_path) if targets_path.is_file() else []
        transaction.stage(TARGETS, bop_json_list(merged_targets(existing, targets_bop19(infos, obj_id, number), number)))
        entry = {"split": SPLIT, "scene_id": number, "obj_id": obj_id, "category": reconstruction.category,
                 "symmetry": reconstruction.symmetry, "images": images}
        return entry, [folder], []

    return export_unit(out, name, "bop", prepare, finish)


def reserve_scene_ids(out: str | Path, names: list[str]) -> dict[str, int]:
    """The scene ids a batch's exports of ``names`` get, in this order (:func:`reconstruct.export_index.reserve_numbers`)."""
    out = Path(out)
    return reserve_numbers(read_index(out), names, "scene_id", _taken(out) if out.is_dir() else set())
