"""The 3D scene: the frame's coloured points, the box with its gizmo and face handles, the camera, previews.

World frame = the current frame's OpenCV camera frame (metres, the scene's up is -y). Points are
sent as float32 relative to their median (viser's default float16 would cost about 1 mm at 1.5 m).
The box geometry, the accumulated model and the mesh preview hang below the box's gizmo node, in
object coordinates, so they move with the gizmo while it is dragged.
"""

from __future__ import annotations

import numpy as np
import viser
from scipy.spatial.transform import Rotation

from evaluate.geometry import BOX_EDGES, box_corners

from .app_frames import DisplayFrame
from .app_views import AXIS_COLORS, TINT_OPACITY, TINTED_FACES, edge_axes, face_centre, face_corners, sensor_fov

BOX = "/box"
#: Face handles: (name, axis, sign).
FACES = tuple((f"{'xyz'[a]}{'+' if s > 0 else '-'}", a, s) for a in range(3) for s in (1, -1))


def wxyz(orientation_xyzw) -> np.ndarray:
    """SciPy x y z w quaternion to viser's w x y z."""
    q = np.asarray(orientation_xyzw, dtype=np.float64)
    return np.array([q[3], q[0], q[1], q[2]])


def xyzw(orientation_wxyz) -> np.ndarray:
    """viser's w x y z quaternion to SciPy x y z w."""
    q = np.asarray(orientation_wxyz, dtype=np.float64)
    return np.array([q[1], q[2], q[3], q[0]])


def face_frame(axis: int, sign: int) -> np.ndarray:
    """w x y z rotation taking a handle's local +x to the face's outward normal (box frame)."""
    normal = np.zeros(3)
    normal[axis] = sign
    helper = np.array([0.0, 0.0, 1.0]) if axis != 2 else np.array([1.0, 0.0, 0.0])
    second = np.cross(helper, normal)
    second /= np.linalg.norm(second)
    third = np.cross(normal, second)
    return wxyz(Rotation.from_matrix(np.stack([normal, second, third], axis=1)).as_quat())


def box_quad(extents, axis: int, sign: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (4, 3) and two-sided faces (4, 3) of one box face, object frame."""
    corners = box_corners(extents)[face_corners(axis, sign)]
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]])
    return corners, faces


class SceneView:
    """Draws the session into a viser scene; holds the scene handles."""

    def __init__(self, server: viser.ViserServer, camera, point_size: float = 0.004) -> None:
        self.server = server
        self.scene = server.scene
        self.camera = camera
        self.point_size = point_size
        self.scene.set_up_direction("-y")
        self.gizmo = self.scene.add_transform_controls(BOX, scale=0.12, depth_test=False, opacity=0.9)
        self.face_handles: dict[str, viser.TransformControlsHandle] = {}
        self.tints: dict[str, viser.MeshHandle] = {}  # by TintedFace.name
        self.face_labels: dict[str, viser.LabelHandle] = {}  # by TintedFace.name: "top", "front" on the faces
        self.cloud = None
        self.frustum = None
        self.model = None
        self.mesh = None
        self.mesh_parts: list = []
        self.mesh_vertices = np.zeros((0, 3), np.float32)  # the preview's vertices, object frame
        self.extents = None
        self.show_faces = True
        self.handles_active = True  # False while the frame shows a borrowed box: a click then places the box
        self._box_key = None
        self.place_face_handles(np.full(3, 0.1))

    # --- frame ---------------------------------------------------------------------------
    def show_frame(self, frame: DisplayFrame, image: np.ndarray | None = None) -> None:
        """Replace the point cloud (float32, relative to a point of the cloud) and the frustum's image."""
        origin = frame.origin
        relative = (frame.points - origin.astype(np.float32)).astype(np.float32)
        self.cloud = self.scene.add_point_cloud(
            "/cloud", relative, frame.colors, point_size=self.point_size, precision="float32", point_shape="square", point_shading="flat", position=origin
        )
        self.show_image(frame.image if image is None else image, frame.median_depth)

    def show_image(self, image: np.ndarray, median_depth: float = 1.0) -> None:
        """The camera frustum at the sensor with the (annotated) colour image on its far plane."""
        small = np.asarray(image)
        cam = self.camera
        if self.frustum is not None:
            self.frustum.image = small  # only the image changes: no new scene node
            return
        self.frustum = self.scene.add_camera_frustum(
            "/frustum", fov=sensor_fov(cam), aspect=cam.width / cam.height, scale=min(0.15, 0.3 * median_depth),
            image=small, format="jpeg", jpeg_quality=80, color=(230, 180, 40), thickness=2.0, thickness_units="screen",
            visible=False,  # shown on request (View > Show camera)
        )

    # --- box -----------------------------------------------------------------------------
    def show_pose(self, position, orientation) -> None:
        """Move the gizmo (and the box below it) to a pose (camera frame)."""
        self.gizmo.position = np.asarray(position, dtype=np.float64)
        self.gizmo.wxyz = wxyz(orientation)

    def show_box(self, extents, own_pose: bool) -> None:
        """Redraw the box geometry when its extents or its own/borrowed look changed (switching frames rarely does)."""
        key = (tuple(np.round(np.asarray(extents, dtype=np.float64), 9)), bool(own_pose))
        if key == self._box_key:
            return
        self._draw_box(extents, own_pose)
        self.set_handles(own_pose)
        self._box_key = key

    def set_handles(self, active: bool) -> None:
        """The gizmo's arrows and rings and the faces' arrows, or none of them. A frame without its own box shows the
        nearest frame's without handles: drawn over the object (depth_test off), they caught the click meant to place
        the box on it (the browser's pointer goes to the handle, and the scene's click never comes)."""
        self.handles_active = bool(active)
        self.gizmo.disable_axes = self.gizmo.disable_sliders = self.gizmo.disable_rotations = not active
        self.set_face_handles(self.show_faces)

    def set_face_handles(self, show: bool) -> None:
        """Show the faces' arrows (the View toggle), where the box has handles at all (:meth:`set_handles`)."""
        self.show_faces = bool(show)
        for handle in self.face_handles.values():
            handle.visible = self.show_faces and self.handles_active

    def _draw_box(self, extents, own_pose: bool) -> None:
        """Box geometry below the gizmo: axis-coloured edges, the tinted faces (app_views.TINTED_FACES) and their
        words ("top", "front") at their centres.

        A frame without its own pose shows the borrowed box dashed-looking (thin, grey edges).
        """
        extents = np.asarray(extents, dtype=np.float64)
        corners = box_corners(extents)
        segments = corners[BOX_EDGES]  # (12, 2, 3)
        colors = AXIS_COLORS[edge_axes()] if own_pose else np.full((12, 3), 160, dtype=np.uint8)
        self.scene.add_line_segments(
            f"{BOX}/edges", segments.astype(np.float32), np.repeat(colors[:, None, :], 2, axis=1),
            thickness=3.0 if own_pose else 1.5, thickness_units="screen",
        )
        for face in TINTED_FACES:
            vertices, faces = box_quad(extents, face.axis, face.sign)
            self.tints[face.name] = self.scene.add_mesh_simple(
                f"{BOX}/{face.name}", vertices, faces, color=face.color, opacity=TINT_OPACITY, side="double", cast_shadow=False, receive_shadow=False
            )
            self.face_labels[face.name] = self.scene.add_label(f"{BOX}/{face.name}_label", face.label, position=face_centre(extents, face.axis, face.sign),
                                                               anchor="center-center", font_screen_scale=0.9)
        if self.extents is None or not np.array_equal(self.extents, extents):
            self.place_face_handles(extents)
        self.extents = extents

    def place_face_handles(self, extents) -> None:
        """One single-axis gizmo per face (viser's gizmo cannot scale): dragging it moves that face."""
        for name, axis, sign in FACES:
            position = np.zeros(3)
            position[axis] = sign * extents[axis] / 2
            handle = self.face_handles.get(name)
            if handle is None:
                handle = self.scene.add_transform_controls(
                    f"{BOX}/face_{name}", scale=0.04, active_axes=(True, False, False), disable_rotations=True,
                    disable_sliders=True, depth_test=False, wxyz=face_frame(axis, sign), position=position,
                    visible=self.show_faces and self.handles_active,
                )
                self.face_handles[name] = handle
            else:
                handle.position = position
                handle.wxyz = face_frame(axis, sign)

    # --- previews ------------------------------------------------------------------------
    def show_model(self, points_obj: np.ndarray | None, colors: np.ndarray | None = None) -> None:
        """Accumulated object points (object frame) below the box, or remove them (None)."""
        if self.model is not None:
            self.model.remove()
            self.model = None
        if points_obj is not None and len(points_obj):
            colors = (255, 140, 0) if colors is None else colors
            self.model = self.scene.add_point_cloud(f"{BOX}/model", np.asarray(points_obj, dtype=np.float32), colors, point_size=self.point_size * 0.6, precision="float32", point_shading="flat")

    def show_mesh(self, vertices: np.ndarray | None, faces: np.ndarray | None = None, face_colors: np.ndarray | None = None) -> None:
        """A mesh preview (object frame) below the box, or remove it (None). ``face_colors`` (F, 3) uint8 tint its faces
        (what was seen: reconstruct.seen.LABEL_COLOURS): one mesh per colour, as viser's meshes take one colour each."""
        for handle in self.mesh_parts:
            handle.remove()
        self.mesh_parts = []
        self.mesh = None
        if vertices is None or not len(vertices):
            return
        vertices, faces = np.asarray(vertices, dtype=np.float32), np.asarray(faces)
        if face_colors is None:
            face_colors = np.broadcast_to(np.array([240, 200, 120], np.uint8), (len(faces), 3))
        colours, which = np.unique(np.asarray(face_colors, np.uint8), axis=0, return_inverse=True)
        for k, colour in enumerate(colours):  # three colours at most
            part = self.scene.add_mesh_simple(f"{BOX}/mesh_{k}", vertices, faces[which.reshape(-1) == k], color=tuple(int(c) for c in colour),
                                              opacity=0.85, flat_shading=False, side="double")
            self.mesh_parts.append(part)
        self.mesh = self.mesh_parts[0]
        self.mesh_vertices = vertices
