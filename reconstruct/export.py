"""REDWOOD75-format export: ``OUT/annotations.json``, ``OUT/<sequence>.obj``, masks and report.

Layout written (``OUT`` may already hold other sequences; this sequence's entries are added or
replaced, the rest kept):

- ``OUT/annotations.json``: ``{sequence: {category, mesh, scale, pose_anns: [{position,
  orientation, rgb_file, depth_file}]}}`` exactly as REDWOOD75 (cpas_toolbox's
  ``AnnotatedRedwoodDataset`` reads it): REDWOOD75's raw object axes (raw x = ShapeNet z,
  raw y = -ShapeNet y, raw z = ShapeNet x), ``scale`` = HALF extents in raw axes, positions in
  the OpenCV camera frame (metres), orientation quaternion x, y, z, w (object to camera).
- ``OUT/<sequence>.obj``: the mesh, raw axes, metres, centred on its tight box.
- ``OUT/masks/<sequence>/<frame id>.png``: instance masks, uint8 0 / 255 (see :mod:`reconstruct.masks`).
- ``OUT/reports/<sequence>.json`` and ``OUT/reports/<sequence>.png``: report and preview;
  ``OUT/reports/<sequence>.ply``: the mesh (ShapeNet axes) coloured by what was seen (:mod:`reconstruct.seen`:
  grey observed, blue inferred from symmetry, orange unseen), the shares and the box faces in the report.

A sequence's files are written as one unit (:mod:`reconstruct.transaction`, through
:func:`reconstruct.export_index.export_unit` as the BOP and NOCS exports are): staged beside OUT, swapped in
by renames with the previous files kept until ``annotations.json``, written last, commits them; a killed
export is rolled back (or finished) by the next export into OUT. A folder that holds another format's export is
refused. Every path is built from plain names and
checked to stay inside OUT (:mod:`sequences.names`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from evaluate.geometry import matrix_to_quat, shapenet_to_raw_extents, shapenet_to_raw_points, shapenet_to_raw_pose
from sequences.annotation import Annotation
from sequences.names import check_name
from sequences.reader import Sequence

from .export_index import export_unit
from .masks import mask_png_bytes, render_masks
from .pipeline import Reconstruction
from .report import preview_png_bytes, report_json
from .seen import coloured_ply


def raw_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The mesh in REDWOOD75's raw axes (a proper rotation: the winding stays outward)."""
    return trimesh.Trimesh(shapenet_to_raw_points(mesh.vertices), mesh.faces.copy(), process=False)


def obj_text(mesh: trimesh.Trimesh, name: str) -> str:
    """OBJ text (vertices to 8 decimals, faces) of a mesh already in raw axes: the lines trimesh's exporter writes,
    formatted in one pass (a third of its time)."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64).ravel().tolist()
    faces = (np.asarray(mesh.faces, dtype=np.int64) + 1).ravel().tolist()
    return "".join([f"# {name}: reconstruct-sequence (REDWOOD75 raw axes, metres)\n", "v %.8f %.8f %.8f\n" * (len(vertices) // 3) % tuple(vertices),
                    "f %d %d %d\n" * (len(faces) // 3) % tuple(faces)])


def sequence_entry(reconstruction: Reconstruction, sequence: Sequence) -> dict:
    """The ``annotations.json`` entry of one sequence (REDWOOD75 raw axes)."""
    pose_anns = []
    for frame_id in sorted(reconstruction.poses, key=sequence.index):
        files = sequence.frames[sequence.index(frame_id)]
        T = shapenet_to_raw_pose(reconstruction.poses[frame_id])
        pose_anns.append(
            {
                "position": [float(x) for x in T[:3, 3]],
                "orientation": [float(x) for x in matrix_to_quat(T[:3, :3])],
                "rgb_file": files.color_path.name,
                "depth_file": files.depth_path.name,
            }
        )
    return {
        "scale": [float(x) for x in shapenet_to_raw_extents(reconstruction.extents) / 2],
        "pose_anns": pose_anns,
        "mesh": f"{reconstruction.sequence}.obj",
        "category": reconstruction.category,
    }


def export_redwood(reconstruction: Reconstruction, sequence: Sequence, annotation: Annotation, out_dir: str | Path, masks: bool = True) -> Path:
    """Write one reconstruction into ``out_dir`` (see the module docstring); returns ``annotations.json``'s path.

    One unit of :func:`reconstruct.export_index.export_unit`: everything is rendered and staged without OUT's lock
    (a broken ``annotations.json``, or a folder of another format, is refused first), then swapped in under it with
    ``annotations.json`` last; the sequence's mask folder is swapped whole (a re-export with fewer frames leaves
    none of the old masks). A failure or a kill leaves ``out_dir``'s previous export whole.
    """
    out_dir = Path(out_dir)
    name = check_name(reconstruction.sequence, "sequence name", out_dir)

    def prepare(stage) -> dict:
        entry = sequence_entry(reconstruction, sequence)
        frame_masks: dict[str, np.ndarray] = {}
        if masks:
            frame_masks = reconstruction.masks()
            if frame_masks is None:  # none rendered with it, or its mesh or poses replaced since
                frame_masks = render_masks(reconstruction.mesh, reconstruction.poses, sequence.camera, sequence.depth)
            for frame_id, mask in frame_masks.items():
                stage(f"masks/{name}/{check_name(frame_id, 'frame id', out_dir)}.png", mask_png_bytes(mask))
        report = dict(reconstruction.report)
        report["masks"] = f"masks/{name}/" if masks else None
        report["mesh_file"] = f"{name}.obj"
        if sequence.camera.K.tolist() != [[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]]:
            report["warning"] = "camera differs from REDWOOD75's (fx = fy = 525, cx = 319.5, cy = 239.5), which cpas_toolbox assumes"
        stage(entry["mesh"], obj_text(raw_mesh(reconstruction.mesh), name).encode("utf-8"))
        stage(f"reports/{name}.json", report_json(report).encode("utf-8"))
        stage(f"reports/{name}.png", preview_png_bytes(reconstruction, sequence, frame_masks))
        if reconstruction.surface is not None:  # what was seen: grey observed, blue inferred, orange unseen
            stage(f"reports/{name}.ply", coloured_ply(reconstruction.mesh, reconstruction.surface))
        return entry

    def finish(index: dict, transaction, entry: dict) -> tuple[dict, list[str], list[str]]:
        return entry, [], []  # (the transaction swaps masks/<name> whole)

    return export_unit(out_dir, reconstruction.sequence, "redwood75", prepare, finish)
