"""The model panel: the accumulated object points, the carved mesh preview, and the ground-truth export.

The accumulated model gathers the box-cropped points of the posed frames into the object frame
(it shows at once whether the boxes agree). The mesh preview and the export go through the
reconstruct pipeline (issue 4), in a worker thread with progress; without it the panel says so.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sequences.pointcloud import frame_points

from .app_review import is_flagged

if TYPE_CHECKING:
    from .app import App

#: Voxel size of the quick mesh preview (m); the export uses the pipeline's default (2 mm).
PREVIEW_VOXEL = 0.004
MODEL_FRAMES = 24


def accumulate_model(sequence, annotation, max_frames: int = MODEL_FRAMES, stride: int = 2, margin: float = 0.005) -> tuple[np.ndarray, np.ndarray]:
    """Object-frame points (N, 3) and colours (N, 3) uint8 of up to ``max_frames`` posed frames, cropped by the box."""
    ids = [f for f in sequence.ids if f in annotation.frames]
    if not ids:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    chosen = [ids[i] for i in np.unique(np.linspace(0, len(ids) - 1, min(max_frames, len(ids))).round().astype(int))]
    points, colors = [], []
    for frame_id in chosen:  # a loop over frames (not points): at most max_frames
        pose = annotation.frames[frame_id]
        cloud = frame_points(sequence, frame_id, box=(pose.position, pose.orientation, annotation.extents), margin=margin, stride=stride)
        R = pose.matrix[:3, :3]
        points.append((cloud.points - pose.position) @ R)  # p_obj = R^T (p_cam - t)
        colors.append(cloud.colors)
    return np.concatenate(points), np.concatenate(colors)


def reconstruct_module():
    """(reconstruct.pipeline, reconstruct.export) or None when the reconstruct pipeline is not installed."""
    try:
        from reconstruct import export, pipeline
    except ImportError:
        return None
    if not (hasattr(pipeline, "reconstruct_sequence") and hasattr(export, "export_redwood")):
        return None
    return pipeline, export


class ModelPanel:
    """GUI for the accumulated model, the mesh preview and the export."""

    def __init__(self, app: "App") -> None:
        self.app = app
        self.worker: threading.Thread | None = None
        self._model_worker: threading.Thread | None = None
        self._model_dirty = False
        self._model_running = False
        self._model_lock = threading.Lock()
        seq = app.sequence
        gui = app.server.gui
        with gui.add_folder("Model and export", expand_by_default=False):
            self.show_model = gui.add_checkbox("Show accumulated points", initial_value=False, hint="box-cropped points of the posed frames, in the box")
            self.preview = gui.add_button("Preview mesh", hint=f"carve the posed frames at {PREVIEW_VOXEL * 1000:.0f} mm voxels")
            self.hide_mesh = gui.add_button("Hide mesh")
            self.out_dir = gui.add_text("Export folder", initial_value=str(Path(seq.root).resolve().parent / f"{seq.name}_gt"),
                                        hint="annotations.json, the mesh, masks and reports go here (other sequences' files stay)")
            self.export = gui.add_button("Export ground truth", hint="reconstruct at 2 mm and write annotations.json and the mesh")
            self.progress = gui.add_progress_bar(0.0, animated=False)
            self.info = gui.add_markdown("" if reconstruct_module() else "Reconstruct pipeline (reconstruct.pipeline/export) is not installed: preview and export are unavailable.")
        self.show_model.on_update(lambda _: self.refresh_model())
        self.preview.on_click(lambda _: self.start(self._preview))
        self.hide_mesh.on_click(lambda _: app.scene.show_mesh(None))
        self.export.on_click(lambda _: self.start(self._export))
        app.state.subscribe(self._on_change)

    @property
    def busy(self) -> bool:
        return self.worker is not None and self.worker.is_alive()

    def _on_change(self, kind: str) -> None:
        if kind == "document" and self.show_model.value:
            self.refresh_model()

    def refresh_model(self, wait: bool = False) -> None:
        """Recompute and show (or hide) the accumulated points, in a background thread.

        Changes that arrive while it runs are coalesced into one more run (reading up to
        :data:`MODEL_FRAMES` frames takes a while; edits must not wait for it).
        """
        app = self.app
        if not self.show_model.value:
            app.scene.show_model(None)
            return
        with self._model_lock:
            self._model_dirty = True
            if not self._model_running:  # (a flag, not is_alive(): a finishing worker must not swallow this change)
                self._model_running = True
                self._model_worker = threading.Thread(target=self._model_loop, daemon=True, name="accumulate")
                self._model_worker.start()
            worker = self._model_worker
        if wait:
            worker.join()

    def _model_loop(self) -> None:
        app = self.app
        while True:
            with self._model_lock:
                if not self._model_dirty:
                    self._model_running = False
                    return
                self._model_dirty = False
            document = app.state.document()
            try:
                points, colors = accumulate_model(app.sequence, document)
            except Exception as error:  # a bad frame must not end the session
                app.say(f"Accumulated points failed: {error}")
                continue
            if self.show_model.value:
                app.scene.show_model(points, colors)

    def start(self, job, wait: bool = False) -> bool:
        """Run a preview or export job in the worker thread (one at a time)."""
        if reconstruct_module() is None:
            self.app.say("Preview and export need the reconstruct pipeline, which is not installed.")
            return False
        if self.busy:
            self.app.say("A reconstruction is already running.")
            return False
        if not self.app.state.document().frames:
            self.app.say("Place a box in some frames first.")
            return False
        self.progress.value = 0.0
        self.worker = threading.Thread(target=self._run, args=(job,), daemon=True, name="reconstruct")
        self.worker.start()
        if wait:
            self.worker.join()
        return True

    def _progress(self, stage: str, done: int, total: int) -> None:
        self.progress.value = 100.0 * done / max(total, 1)
        self.info.content = f"{stage}: {done}/{total}"

    def _run(self, job) -> None:
        start = time.perf_counter()
        try:
            message = job()
        except Exception as error:  # a failed reconstruction leaves the session intact
            message = f"Failed: {error}"
        self.progress.value = 100.0
        self.info.content = f"{message} ({time.perf_counter() - start:.1f} s)"
        self.app.say(self.info.content)

    def _preview(self) -> str:
        pipeline, _ = reconstruct_module()
        document = self.app.state.document()
        rec = pipeline.reconstruct_sequence(self.app.sequence, document, voxel_size=PREVIEW_VOXEL, progress=self._progress)
        # the mesh is centred on its tight box; the box node is the annotated object frame
        vertices = np.asarray(rec.mesh.vertices) + np.asarray(getattr(rec, "centre_shift", np.zeros(3)))
        surface = getattr(rec, "surface", None)
        colors = None
        if surface is not None:  # a face takes its vertices' most trusted label, as in the report's shares
            from reconstruct.seen import LABEL_COLOURS

            colors = LABEL_COLOURS[surface.labels[np.asarray(rec.mesh.faces)].min(axis=1)]
        self.app.scene.show_mesh(vertices, np.asarray(rec.mesh.faces), colors)
        extents = ", ".join(f"{e * 1000:.1f}" for e in rec.extents)
        message = f"Mesh preview: {len(rec.mesh.faces)} faces, tight box {extents} mm"
        if surface is not None:
            shares = surface.shares
            message += (f"; surface {shares['observed']:.0%} observed (grey), {shares['inferred']:.0%} inferred from symmetry (blue), "
                        f"{shares['unseen']:.0%} never seen (orange)")
            unmeasured = surface.unmeasured_faces()
            if unmeasured:
                message += f". The box's {', '.join(face for face, _ in unmeasured)} rests on unseen surface: {unmeasured[0][1]}."
        return message

    def _export(self) -> str:
        pipeline, export = reconstruct_module()
        document = self.app.state.document()
        out = Path(str(self.out_dir.value)).expanduser()
        flagged = sum(1 for pose in document.frames.values() if is_flagged(pose))
        rec = pipeline.reconstruct_sequence(self.app.sequence, document, progress=self._progress)
        path = export.export_redwood(rec, self.app.sequence, document, out)
        if flagged:
            return (f"Exported ground truth to {path}. Warning: {flagged} frame{'s are' if flagged > 1 else ' is'} still flagged: "
                    "their poses are exported unreviewed (Review: fix or accept them, then export again)")
        return f"Exported ground truth to {path}"

    def close(self) -> None:
        pass
