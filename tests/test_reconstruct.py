"""reconstruct: carving, meshing, tight box, masks and the pipeline against analytic scenes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from reconstruct import carving, meshing
from reconstruct.masks import MeshRenderer, render_masks, visible_mask
from reconstruct.pipeline import reconstruct_sequence
from reconstruct.tight_box import fit_tight_box, recentre_pose
from sequences.annotation import load_annotation
from sequences.camera import Camera
from sequences.errors import InputError
from sequences.reader import open_sequence
from test_reconstruct_scenes import cup_mesh, fscore, orbit_poses, render_depth, write_scene, y_cylinder


@pytest.fixture(scope="module")
def box_scene(tmp_path_factory):
    mesh = trimesh.creation.box([0.06, 0.1, 0.04])
    return write_scene(tmp_path_factory.mktemp("box") / "box_0001", mesh, n_frames=30, noise=True, hand=True)


@pytest.fixture(scope="module")
def cup_scene(tmp_path_factory):
    return write_scene(tmp_path_factory.mktemp("cup") / "cup_0001", cup_mesh(), n_frames=40, noise=True, hand=True, category="mug")


def _load(scene):
    return open_sequence(scene.root), load_annotation(scene.root / "annotation.yaml")


# --- carving -------------------------------------------------------------------------------------


def test_grid_covers_box_plus_margin_and_is_centred():
    grid = carving.make_grid([0.1, 0.05, 0.02], 0.002, margin=0.01)
    assert grid.shape == (60, 35, 20)
    centres = grid.centres()
    np.testing.assert_allclose(centres.mean(axis=0), 0, atol=1e-6)
    np.testing.assert_allclose(centres.max(axis=0) - centres.min(axis=0), [0.118, 0.068, 0.038], atol=1e-6)
    with pytest.raises(ValueError):
        carving.make_grid([0.1, 0.1, 0.1], 0.0)


def test_depth_sigma_model():
    assert carving.depth_sigma(0.4) == pytest.approx(0.0012)
    assert carving.depth_sigma(1.4) == pytest.approx(0.0012 + 0.0019)


def test_carving_a_single_frame_keeps_only_the_shadow():
    # one camera looking down +z at a wall 1 m away; voxels in front are free, behind it unknown
    camera = Camera(fx=100, fy=100, cx=49.5, cy=49.5, width=100, height=100)
    grid = carving.make_grid([0.2, 0.2, 0.2], 0.01, margin=0.0)
    pose = np.eye(4)
    pose[2, 3] = 1.0  # object centre on the wall plane
    depth = np.ones((100, 100), np.float32)
    depth[:, :50] = 0  # left half: no measurement
    result = carving.carve(grid, [("a", depth, pose)], camera, k=0)
    z = grid.axis_coordinates(2)
    x = grid.axis_coordinates(0)
    occupied = result.occupied
    tol = 2 * carving.depth_sigma(1.0) + np.sqrt(3) / 2 * 0.01
    in_front = z < -tol
    right = x > 0.005
    assert not occupied[np.ix_(right, np.ones(20, bool), in_front)].any()  # seen free
    assert occupied[np.ix_(~right, np.ones(20, bool), in_front)].all()  # no depth: unknown, kept
    assert occupied[:, :, z > 0].all()  # behind the wall: unknown, kept


def _cube_one_metre_ahead():
    """A 100x100 px camera (f = 100 px), a 2 cm grid of 2 mm voxels and the pose putting it 1 m ahead."""
    camera = Camera(fx=100, fy=100, cx=49.5, cy=49.5, width=100, height=100)
    grid = carving.make_grid([0.02, 0.02, 0.02], 0.002, margin=0.0)
    pose = np.eye(4)
    pose[2, 3] = 1.0
    return camera, grid, pose


def test_veto_keeps_voxels_that_other_frames_see_inside():
    # one frame sees past everything (a pose error, say); three see a surface at 0.998 m
    camera, grid, pose = _cube_one_metre_ahead()
    far = np.full((100, 100), 1.5, np.float32)
    surface = np.full((100, 100), 0.998, np.float32)
    frames = [("a", far, pose)] + [(f"b{i}", surface, pose) for i in range(3)]
    z = grid.axis_coordinates(2) + 1.0  # camera depth of each z layer
    vetoed = carving.carve(grid, frames, camera, k=0, veto=0.5).occupied
    plain = carving.carve(grid, frames, camera, k=0, veto=None).occupied
    # kept: the layers 0 .. tol (5.5 mm) behind the surface, seen there 3 times and free once
    expected = (z >= 0.998) & (z <= 0.998 + 2 * carving.depth_sigma(0.998) + np.sqrt(3) * 0.001)
    assert expected.sum() == 3
    np.testing.assert_array_equal(vetoed.all(axis=(0, 1)), expected)
    np.testing.assert_array_equal(vetoed.any(axis=(0, 1)), expected)
    assert not plain.any()


def test_block_decisions_give_the_votes_of_each_voxel_decided_alone():
    # a cup seen from 6 orbit poses, 5 % of the pixels dropped, one camera inside the grid
    camera = Camera(fx=120, fy=120, cx=79.5, cy=59.5, width=160, height=120)
    mesh = cup_mesh()
    rng = np.random.default_rng(3)
    poses = orbit_poses(6, distance=0.3, seed=1)
    poses[5][:3, 3] = [0.0, 0.0, 0.02]  # camera inside the grid: voxels behind it are unknown
    frames = []
    for i, pose in enumerate(poses):
        depth = render_depth([mesh.copy().apply_transform(pose)], camera)
        depth[rng.random(depth.shape) < 0.05] = 0.0
        frames.append((str(i), depth, pose))
    grid = carving.make_grid(mesh.extents, 0.004)
    # independent truth: every voxel centre projected on its own (float64), votes counted frame by frame
    centres = grid.centres(np.float64)
    free, behind = np.zeros(grid.size, int), np.zeros(grid.size, int)
    tol_half = np.sqrt(3) / 2 * grid.voxel_size
    for _, depth, pose in frames:
        cam = centres @ pose[:3, :3].T + pose[:3, 3]
        z = cam[:, 2]
        ok = z > 1e-3
        u = np.floor(camera.fx * cam[:, 0] / np.where(ok, z, 1) + camera.cx + 0.5).astype(int)
        v = np.floor(camera.fy * cam[:, 1] / np.where(ok, z, 1) + camera.cy + 0.5).astype(int)
        ok &= (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        d = np.where(ok, depth[np.clip(v, 0, camera.height - 1), np.clip(u, 0, camera.width - 1)], 0.0).astype(np.float64)
        tol = np.float32(2.0) * carving.depth_sigma(d.astype(np.float32)) + np.float32(tol_half)
        ok &= d > 0
        alive = free <= 6  # the settle rule: voxels seen free in more than max(k, settle) frames stop counting
        free += ok & alive & (z < (d.astype(np.float32) - tol))
        behind += ok & alive & (z >= d) & (z <= (d.astype(np.float32) + tol))
    for block in (1, 3, 4):
        result = carving.carve(grid, frames, camera, k=1, veto=0.5, settle=6, block=block)
        np.testing.assert_array_equal(result.free_count.reshape(-1), np.minimum(free, 7))
        np.testing.assert_array_equal(result.behind_count.reshape(-1), behind)
    assert 0 < (free > 0).mean() < 1 and behind.sum() > 0


def _cavity_beside_a_surface():
    """The camera, the grid and four frames from one camera 1 m from it: left half (x < 0) a cavity that one frame sees
    into (depth 1.5 m) while the others see a nearer wall (0.95 m); right half a surface at 0.998 m that three frames
    see and the same outlier frame sees past."""
    camera, grid, pose = _cube_one_metre_ahead()
    outlier = np.full((100, 100), 1.5, np.float32)
    seen = np.full((100, 100), 0.998, np.float32)
    seen[:, :50] = 0.95
    return camera, grid, [("outlier", outlier, pose)] + [(f"b{i}", seen, pose) for i in range(3)]


def test_unbacked_voxels_seen_free_once_are_carved_and_backed_ones_kept():
    # no frame sees the cavity (x < 0) just behind a surface; three see the surface's layers (x > 0) so
    camera, grid, frames = _cavity_beside_a_surface()
    x = grid.axis_coordinates(0)
    z = grid.axis_coordinates(2) + 1.0  # camera depth of each z layer
    band = (z >= 0.998) & (z <= 0.998 + 2 * carving.depth_sigma(0.998) + np.sqrt(3) * 0.001)  # just behind the surface
    assert band.sum() == 3 and (z > 0.95 + 0.01).all()  # the wall at 0.95 m backs no voxel
    result = carving.carve(grid, frames, camera, k=1, veto=0.5, unbacked=0)
    np.testing.assert_array_equal(result.free_count[x < 0].max(), 1)  # the cavity: free in one frame only
    occupied = result.occupied
    assert not occupied[x < 0].any()  # one free vote and no evidence of the object: carved
    right = occupied[x > 0]
    np.testing.assert_array_equal(right.all(axis=(0, 1)), band)  # free once but seen inside three times: kept
    np.testing.assert_array_equal(right.any(axis=(0, 1)), band)  # deeper, free once and never backed: carved
    # without the rule, k = 1 keeps every voxel seen free only once: the cavity, the deep layers and
    # those within the free tolerance in front of the surface
    plain = carving.carve(grid, frames, camera, k=1, veto=0.5, unbacked=None).occupied
    assert plain[x < 0].all()
    tol = 2 * carving.depth_sigma(0.998) + np.sqrt(3) * 0.001
    np.testing.assert_array_equal(plain[x > 0].all(axis=(0, 1)), z >= 0.998 - tol)


def test_the_box_bounds_what_no_frame_saw_inside_even_where_some_frame_saw_it_free():
    # the scene above without the unbacked rule: k = 1 keeps every voxel seen free once. A box 4 mm wide in x leaves
    # 8 mm of the 20 mm grid outside on either side: there only the layers three frames saw just behind the surface stay
    camera, grid, frames = _cavity_beside_a_surface()
    result = carving.carve(grid, frames, camera, k=1, veto=0.5, unbacked=None)
    assert result.free_count.min() >= 1  # every voxel seen free by the outlier: none is unobserved
    x = grid.axis_coordinates(0)
    z = grid.axis_coordinates(2) + 1.0
    band = (z >= 0.998) & (z <= 0.998 + 2 * carving.depth_sigma(0.998) + np.sqrt(3) * 0.001)
    bounded = carving.bound_by_box(result.occupied, result.behind_count, grid, [0.004, 0.04, 0.04])
    inside = np.abs(x) <= 0.002
    np.testing.assert_array_equal(bounded[inside], result.occupied[inside])  # inside the box: the carving's verdict
    outside = bounded[~inside]
    np.testing.assert_array_equal(outside[x[~inside] < 0].any(axis=(0, 1)), np.zeros_like(band))  # the cavity: no evidence
    np.testing.assert_array_equal(outside[x[~inside] > 0].all(axis=(0, 1)), band)  # backed three times: kept
    np.testing.assert_array_equal(outside[x[~inside] > 0].any(axis=(0, 1)), band)  # in front, deeper: free once, gone
    # a box holding the whole grid changes nothing
    np.testing.assert_array_equal(carving.bound_by_box(result.occupied, result.behind_count, grid, [0.03] * 3), result.occupied)


def _shadowed_row(f=525.0, cx=319.5, baseline=0.075, d_near=0.6, d_far=1.5, edge_x=0.0, width=640):
    """One image row by exact geometry: a wall at ``d_far``, a foreground half-plane X >= ``edge_x`` at
    ``d_near``, the projector at X = ``baseline``. Returns (true depth, measured depth: 0 where the
    segment from the seen point to the projector crosses the foreground)."""
    x = np.arange(width)
    sees_near = (x - cx) * d_near / f >= edge_x
    true = np.where(sees_near, d_near, d_far)
    X = (x - cx) * true / f  # the seen point
    crossing = X + (baseline - X) * (true - d_near) / true  # where its way to the projector meets z = d_near
    shadowed = ~sees_near & (crossing >= edge_x)
    return true.astype(np.float32), np.where(shadowed, 0.0, true).astype(np.float32)


def test_shadow_fill_is_never_deeper_than_the_true_surface_and_reaches_the_background():
    true, measured = _shadowed_row()
    hole = measured == 0
    assert 20 < hole.sum() < 40  # 525 * 0.075 * (1/0.6 - 1/1.5) = 39.4 px, less the part the foreground covers
    filled = carving.shadow_free_depth(np.tile(measured, (3, 1)), 525.0)
    assert (filled > 0).all()  # the whole shadow is explained
    assert (filled <= true + 1e-6).all()  # never free in front of a real surface
    edge = np.flatnonzero(hole).max()
    assert (filled[0, edge - 2 : edge + 1] == pytest.approx(0.6))  # next to the occluder (edge_px = 3): its depth
    # farther from the edge the bound goes deeper: 11 px from the edge, less edge_px, of disparity behind the occluder
    assert filled[0, edge - 10] == pytest.approx(1 / (1 / 0.6 - 8 / (525 * 0.075)), rel=1e-5)
    assert filled[0, np.flatnonzero(hole).min()] > 1.2  # the far end of the shadow: free far behind the occluder
    # the projector on the left: mirrored scene, mirrored fill
    mirrored = carving.shadow_free_depth(np.tile(measured[::-1], (3, 1)), 525.0, baseline=-0.075)
    np.testing.assert_allclose(mirrored[:, ::-1], filled)


def test_shadow_fill_leaves_unexplained_holes_unknown():
    _, measured = _shadowed_row()
    depth = np.tile(measured, (4, 1))
    depth[1, 100:110] = 0  # a hole in the wall: no nearer surface beside it
    depth[2, 400:405] = 0  # a hole inside the foreground
    shadow = np.flatnonzero(measured == 0)
    depth[3, shadow.min() - 8 : shadow.min()] = 0  # the shadow run made wider than any shadow of 0.6 on 1.5
    filled = carving.shadow_free_depth(depth, 525.0)
    assert (filled[1, 100:110] == 0).all() and (filled[2, 400:405] == 0).all()
    assert (filled[3, shadow.min() - 8 : shadow.max() + 1] == 0).all()
    assert (filled[1, shadow] > 0).all()  # the real shadow of the same row is still filled
    # a run whose left side is the nearer one is no shadow of this projector
    assert (carving.shadow_free_depth(depth[:, ::-1].copy(), 525.0)[0][measured[::-1] == 0] == 0).all()


def test_carving_with_shadows_frees_voxels_seen_only_through_a_shadow():
    # camera at the origin looking down +z; a wall at 1.5 m, a foreground half-plane at 0.6 m whose
    # shadow hides the wall; a column of voxels at 0.7 m inside the shadow's rays, behind the occluder
    camera = Camera(fx=525, fy=525, cx=319.5, cy=239.5, width=640, height=480)
    true, measured = _shadowed_row()
    depth = np.tile(measured, (480, 1))
    shadow = np.flatnonzero(measured == 0)
    u = shadow.min() + 5  # well inside the shadow: its bound is far deeper than 0.7 m
    grid = carving.VoxelGrid(np.array([(u - 319.5) * 0.7 / 525, -0.01, -0.01]), 0.002, (1, 11, 11))
    pose = np.eye(4)
    pose[2, 3] = 0.7
    frames = [(str(i), depth, pose) for i in range(3)]
    assert carving.carve(grid, frames, camera, k=1, shadows=False).occupied.all()  # missing depth: unknown
    assert not carving.carve(grid, frames, camera, k=1, shadows=True).occupied.any()


def test_revolve_carves_rings_by_their_carved_share():
    grid = carving.make_grid([0.04, 0.02, 0.04], 0.002, margin=0.0)
    X, Z = np.meshgrid(grid.axis_coordinates(0), grid.axis_coordinates(2), indexing="ij")
    radius = np.hypot(X, Z)
    outside = (radius > 0.015)[:, None, :] & np.ones(grid.shape, bool)
    # the -z side was never seen (nothing carved there); a few noisy voxels carved deep inside
    occupied = ~(outside & (Z > -0.004)[:, None, :])
    occupied[10, :, 10] = False
    revolved = carving.revolve_occupancy(occupied, grid, carved_share=0.5)
    full_rings = ((radius > 0.0165) & (radius < 0.019))[:, None, :] & np.ones(grid.shape, bool)  # whole rings inside the grid
    assert not revolved[full_rings].any()  # every side carved as far as the seen sides
    assert revolved[(radius < 0.0145)[:, None, :] & np.ones(grid.shape, bool)].all()  # the odd voxel is refilled
    # seen from a quarter only: a share of 0.5 keeps the rings, 0.2 carves them
    quarter = ~(outside & ((X > 0) & (Z > 0))[:, None, :])
    assert carving.revolve_occupancy(quarter, grid, 0.5)[full_rings].all()
    assert not carving.revolve_occupancy(quarter, grid, 0.2)[full_rings].any()


def test_revolve_counts_the_share_of_the_observed_ring():
    """With observation counts a side never seen does not count against carving, and a thin rim that pose errors
    saw free on 40% of the ring stays: a cylinder of radius 15 mm, true occupancy known per voxel."""
    grid = carving.make_grid([0.04, 0.02, 0.04], 0.002, margin=0.0)
    X, Z = np.meshgrid(grid.axis_coordinates(0), grid.axis_coordinates(2), indexing="ij")
    radius = (np.hypot(X, Z))[:, None, :] * np.ones(grid.shape)
    angle = np.arctan2(Z, X)[:, None, :] * np.ones(grid.shape)
    full_rings = (radius > 0.0165) & (radius < 0.019)
    # seen from a third of the azimuths only, outside carved there: the share of the observed arc carves the ring
    arc = (angle > 0) & (angle < 2 * np.pi / 3)
    occupied = ~((radius > 0.015) & arc)
    assert carving.revolve_occupancy(occupied, grid, 0.5)[full_rings].all()  # share of the whole ring: kept
    revolved = carving.revolve_occupancy(occupied, grid, 0.5, observed=arc | (radius <= 0.015))
    assert not revolved[full_rings].any() and revolved[radius < 0.0145].all()
    # a sixteenth of the ring seen carved is below the share of OBSERVED_FLOOR: a glimpse says nothing of the rest, kept
    glimpse = (angle > 0) & (angle < np.pi / 8)
    assert 1 / 16 < 0.5 * carving.OBSERVED_FLOOR
    revolved = carving.revolve_occupancy(~((radius > 0.015) & glimpse), grid, 0.5, observed=glimpse | (radius <= 0.015))
    assert revolved[full_rings & ~glimpse].all()
    # everything observed; the rim (13.5-15.5 mm: whole rings) carved on 40% of the ring by frames with pose
    # errors: kept at a share of 0.5
    rim = (radius >= 0.0135) & (radius < 0.0155)
    eaten = ~((radius >= 0.0155) | (rim & (angle > 0) & (angle < 0.8 * np.pi)))
    revolved = carving.revolve_occupancy(eaten, grid, 0.5, observed=np.ones(grid.shape, bool))
    assert revolved[rim].all() and not revolved[full_rings].any()
    assert not carving.revolve_occupancy(eaten, grid, 0.3, observed=np.ones(grid.shape, bool))[rim].all()  # 0.3 eats it


# --- meshing -------------------------------------------------------------------------------------


def _sphere_grid(radius=0.03, voxel=0.002):
    grid = carving.make_grid([2 * radius] * 3, voxel, margin=0.006)
    c = grid.centres(np.float64)
    occupied = (np.linalg.norm(c, axis=1) <= radius).reshape(grid.shape)
    occupied[0, 0, 0] = True  # a stray voxel: not the largest component
    return grid, occupied


def test_mesh_of_sphere_is_watertight_outward_and_keeps_its_size():
    grid, occupied = _sphere_grid()
    mesh = meshing.occupancy_mesh(occupied, grid)
    assert mesh.is_watertight and mesh.body_count == 1
    assert mesh.volume > 0  # outward winding
    radii = np.linalg.norm(mesh.vertices, axis=1)
    assert abs(np.median(radii) - 0.03) < 0.0006  # Taubin does not shrink
    assert abs(mesh.volume / (4 / 3 * np.pi * 0.03**3) - 1) < 0.05
    laplacian = meshing.occupancy_mesh(occupied, grid, smoothing="laplacian", iterations=30)
    assert np.median(np.linalg.norm(laplacian.vertices, axis=1)) < np.median(radii)  # plain Laplacian shrinks
    with pytest.raises(ValueError):
        meshing.occupancy_mesh(occupied, grid, smoothing="bogus")
    with pytest.raises(ValueError):
        meshing.occupancy_mesh(np.zeros_like(occupied), grid)


def test_largest_component_fills_enclosed_holes():
    occupied = np.zeros((9, 9, 9), bool)
    occupied[1:8, 1:8, 1:8] = True
    occupied[3:6, 3:6, 3:6] = False  # an enclosed cavity
    occupied[0, 0, 0] = True
    kept = meshing.largest_component(occupied)
    assert kept[4, 4, 4] and not kept[0, 0, 0]
    assert kept.sum() == 7**3
    # holes by one labelling of the background: scipy's iterated-erosion fill on random masks
    from scipy import ndimage

    masks = np.random.default_rng(0).random((4, 12, 11, 10)) < [[[[0.5]]], [[[0.6]]], [[[0.7]]], [[[0.8]]]]
    for mask in masks:
        np.testing.assert_array_equal(meshing.fill_holes(mask), ndimage.binary_fill_holes(mask))
    assert sum(int((meshing.fill_holes(m) & ~m).sum()) for m in masks) > 0  # some holes were filled


# --- tight box -----------------------------------------------------------------------------------


def test_face_components_are_trimesh_s_face_adjacency_components():
    sphere = trimesh.creation.icosphere(3, 0.05)
    far = trimesh.creation.box([0.02, 0.02, 0.02])
    far.apply_translation([0.2, 0, 0])
    touching = trimesh.creation.icosphere(1, 0.01)  # moved to share one vertex with the sphere: apart by its edges
    touching.apply_translation(sphere.vertices[0] - touching.vertices[np.argmin(touching.vertices[:, 0])])
    mesh = trimesh.util.concatenate([sphere, far, touching])
    mesh.merge_vertices()
    a, b = mesh.edges_unique[0]  # a fin: a third face on one of the sphere's edges, which then joins none of them
    mesh = trimesh.Trimesh(np.vstack([mesh.vertices, [[0.0, 0.2, 0.0]]]), np.vstack([mesh.faces, [[a, b, len(mesh.vertices)]]]), process=False)
    ours = meshing.face_components(mesh.faces)
    theirs = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    assert len(np.unique(theirs)) == 4  # sphere, box, touching sphere, fin
    pairs = np.unique(np.stack([ours, theirs], axis=1), axis=0)  # the same partition: labels map one to one
    assert len(pairs) == len(np.unique(ours)) == len(np.unique(theirs))
    assert len(meshing.largest_piece(mesh).faces) == len(sphere.faces)
    assert len(meshing.face_components(np.zeros((0, 3), int))) == 0
    # watertight: every edge held by two faces, as trimesh says
    open_sphere = trimesh.Trimesh(sphere.vertices, sphere.faces[1:], process=False)
    for shape in (sphere, far, mesh, open_sphere, trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int))):
        assert meshing.is_watertight(shape.faces) == shape.is_watertight
    assert meshing.is_watertight(sphere.faces) and not meshing.is_watertight(open_sphere.faces)


def test_tight_box_recentres_mesh_and_keeps_camera_points():
    mesh = trimesh.creation.box([0.02, 0.04, 0.06])
    mesh.apply_translation([0.01, -0.02, 0.005])
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    pose[:3, 3] = [0.1, 0.2, 0.7]
    centred, poses, centre, extents = fit_tight_box(mesh, {"f": pose})
    np.testing.assert_allclose(centre, [0.01, -0.02, 0.005], atol=1e-12)
    np.testing.assert_allclose(extents, [0.02, 0.04, 0.06], atol=1e-12)
    np.testing.assert_allclose(centred.bounds.mean(axis=0), 0, atol=1e-12)
    before = mesh.vertices @ pose[:3, :3].T + pose[:3, 3]
    after = centred.vertices @ poses["f"][:3, :3].T + poses["f"][:3, 3]
    np.testing.assert_allclose(after, before, atol=1e-12)
    np.testing.assert_allclose(recentre_pose(np.eye(4), [1, 2, 3])[:3, 3], [1, 2, 3])


# --- masks ---------------------------------------------------------------------------------------


def test_mask_matches_independent_render_and_drops_occluded_pixels():
    camera = Camera(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)
    mesh = trimesh.creation.box([0.06, 0.1, 0.04])
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", [20, -35, 10], degrees=True).as_matrix()
    pose[:3, 3] = [0.02, -0.01, 0.6]
    posed = mesh.copy()
    posed.apply_transform(pose)
    truth = render_depth([posed], camera)
    depth = MeshRenderer(mesh, camera).depth(pose)
    silhouette = truth < 1.5
    assert (depth > 0).sum() > 1000
    np.testing.assert_array_equal(depth > 0, silhouette)
    np.testing.assert_allclose(depth[silhouette], truth[silhouette], atol=1e-5)
    # a measured depth 3 cm in front of the object on the left half: those pixels are occluded
    measured = np.where(silhouette, truth, 1.5).astype(np.float32)
    measured[:, :160] -= 0.03
    mask = render_masks(mesh, {"a": pose}, camera, {"a": measured})["a"]
    np.testing.assert_array_equal(mask, silhouette & (np.arange(320) >= 160)[None, :])
    # missing depth never occludes; noise within the tolerance neither
    np.testing.assert_array_equal(visible_mask(depth, np.zeros_like(depth)), silhouette)
    np.testing.assert_array_equal(visible_mask(depth, depth - 0.009 * silhouette), silhouette)
    # an object behind the camera renders nothing
    behind = pose.copy()
    behind[2, 3] = -0.6
    assert not MeshRenderer(mesh, camera).depth(behind).any()


def _cast_every_pixel(mesh: trimesh.Trimesh, pose: np.ndarray, camera: Camera) -> np.ndarray:
    """Independent reference: the posed mesh in camera coordinates, one float64-built ray per pixel."""
    import open3d as o3d

    posed = mesh.copy()
    posed.apply_transform(pose)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(posed.vertices.astype(np.float32)), o3d.core.Tensor(posed.faces.astype(np.uint32)))
    directions = camera.pixel_rays().reshape(-1, 3)
    rays = np.concatenate([np.zeros_like(directions), directions], axis=1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(camera.shape)
    return np.where(np.isfinite(hit), hit, 0.0)


def test_renderer_casts_only_its_face_clusters_rectangles_for_the_same_depth():
    # an L of two boxes (a laptop's shape): half of its bounding box's rectangle is background
    camera = Camera(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)
    base = trimesh.creation.box([0.3, 0.01, 0.2])
    lid = trimesh.creation.box([0.3, 0.2, 0.01])
    lid.apply_translation([0, 0.105, -0.095])
    mesh = trimesh.util.concatenate([base, lid])
    renderer = MeshRenderer(mesh, camera, cells=8)
    rng = np.random.default_rng(3)
    rays = rectangles = 0
    for angles in rng.uniform(-60, 60, size=(5, 3)):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_euler("xyz", angles, degrees=True).as_matrix()
        pose[:3, 3] = [0.02, -0.01, 0.7]
        expected, depth = _cast_every_pixel(mesh, pose, camera), renderer.depth(pose)
        assert (expected > 0).sum() > 2000
        # the rays' directions are summed in float32 (the reference's built in float64): a grazing ray may differ
        assert ((depth > 0) != (expected > 0)).sum() <= 2
        both = (depth > 0) & (expected > 0)
        np.testing.assert_allclose(depth[both], expected[both], atol=1e-5)
        uv, _ = camera.project(trimesh.bounds.corners(mesh.bounds) @ pose[:3, :3].T + pose[:3, 3])
        size = np.minimum(np.ceil(uv.max(axis=0)) + 1, [319, 239]) - np.maximum(np.floor(uv.min(axis=0)) - 1, 0) + 1  # the bounding box's rectangle
        assert (expected > 0).sum() <= renderer.cover(pose).sum() <= size.prod()
        rays, rectangles = rays + renderer.cover(pose).sum(), rectangles + size.prod()
    assert rays < 0.8 * rectangles
    # a box reaching behind the camera: every pixel is cast, the depth is still right
    pose = np.eye(4)
    pose[2, 3] = 0.05
    assert renderer.cover(pose).all()
    expected, depth = _cast_every_pixel(mesh, pose, camera), renderer.depth(pose)
    assert (expected > 0).sum() > 1000 and ((depth > 0) != (expected > 0)).sum() <= 2


# --- pipeline on analytic scenes -----------------------------------------------------------------


def test_frames_flagged_for_review_are_posed_but_do_not_carve(box_scene):
    """Six frames whose poses are 12 mm off and flagged (as tracking flags them): by default they are
    exported with the others but left out of the carving; carving with them cuts into the box."""
    from sequences.annotation import FramePose

    sequence, annotation = _load(box_scene)
    bad = sequence.ids[::5]
    for frame_id in bad:
        T = annotation.frames[frame_id].matrix.copy()
        T[:3, 3] += T[:3, :3] @ np.array([0.012, 0.0, 0.0])  # 12 mm along the box's x
        annotation.frames[frame_id] = FramePose.from_matrix(T, "tracked", {"flagged": True, "flag_reason": "test"})
    rec = reconstruct_sequence(sequence, annotation)
    assert set(rec.poses) == set(sequence.ids) and rec.report["flagged_left_out"] == bad
    assert rec.report["frames_used"] == 30 - len(bad) and rec.report["frames_posed"] == 30
    np.testing.assert_allclose(rec.extents, [0.06, 0.1, 0.04], atol=0.003)
    with_flagged = reconstruct_sequence(sequence, annotation, include_flagged=True)
    assert with_flagged.report["frames_used"] == 30 and not with_flagged.report["flagged_left_out"]
    assert np.abs(with_flagged.extents - [0.06, 0.1, 0.04]).max() > 0.005  # the bad frames carve into the box
    # too few unflagged frames to carve with: all are used
    for frame_id in sequence.ids[:26]:
        annotation.frames[frame_id] = FramePose.from_matrix(annotation.frames[frame_id].matrix, "tracked", {"flagged": True})
    assert reconstruct_sequence(sequence, annotation).report["frames_used"] == 30


def test_frames_flagged_only_for_their_spin_still_carve():
    """A frame whose only flag doubts the spin its shape leaves free (a mug's handle hidden) carves; one
    flagged for anything else, also together with the spin, does not."""
    from annotate.tracking.config import TrackingConfig
    from annotate.tracking.quality import document_figures
    from reconstruct.pipeline import carving_frames
    from sequences.annotation import Annotation, FramePose

    config = TrackingConfig(max_free_spin_run=5)
    spin = document_figures({"fitness": 0.9, "free_spin_run": 8, "free_spin_end": False}, config)
    both = document_figures({"fitness": 0.3, "free_spin_run": 8, "free_spin_end": False}, config)
    other = document_figures({"fitness": 0.3}, config)
    assert spin["flagged"] and spin["flag_spin_only"]
    assert both["flagged"] and "flag_spin_only" not in both and "flag_spin_only" not in other
    assert "flagged" not in document_figures({"fitness": 0.9, "free_spin_run": 2, "free_spin_end": False}, config)
    ids = [f"{k:07d}" for k in range(40)]
    extras = {ids[1]: spin, ids[2]: both, ids[3]: other}
    frames = {f: FramePose.from_matrix(np.eye(4), "tracked", extras.get(f, {})) for f in ids}
    annotation = Annotation(sequence="mug", category="mug", symmetry="none", extents=np.full(3, 0.1), frames=frames)
    assert carving_frames(annotation, ids) == [f for f in ids if f not in (ids[2], ids[3])]


def test_box_scene_is_reconstructed_to_the_millimetre(box_scene):
    sequence, annotation = _load(box_scene)
    calls = []
    rec = reconstruct_sequence(sequence, annotation, progress=lambda stage, done, total: calls.append(stage))
    assert rec.mesh.is_watertight and rec.mesh.volume > 0
    np.testing.assert_allclose(rec.extents, [0.06, 0.1, 0.04], atol=0.003)  # the figure; 30 frames at 320x240
    mesh = rec.mesh.copy()
    mesh.apply_translation(rec.centre_shift)  # back to the true object frame
    assert fscore(mesh, box_scene.mesh, 0.005) >= 0.95  # no hand remnants, no erosion
    assert fscore(mesh, box_scene.mesh, 0.01) >= 0.99
    # every pose still maps the object to the same camera points
    frame = next(iter(rec.poses))
    p = box_scene.mesh.vertices
    np.testing.assert_allclose((p - rec.centre_shift) @ rec.poses[frame][:3, :3].T + rec.poses[frame][:3, 3], p @ box_scene.poses[frame][:3, :3].T + box_scene.poses[frame][:3, 3], atol=1e-9)
    assert set(rec.timings) >= {"carve", "mesh", "tight_box"}
    assert rec.report["frames_used"] == 30 and "carve" in calls


def test_nothing_beyond_the_box_grown_by_its_slack_is_object(tmp_path):
    """A hand that never lets go (a sphere fixed against the cube's +x face, 3 cm in radius) is measured in every frame
    and never seen free: only the annotated box tells it from the object. Without the bound it fills the grid's margin
    (15 mm beyond the face); with it, at most the box's 10 % slack (5 mm)."""
    from reconstruct.pipeline import BOX_BOUND_SLACK

    hand = trimesh.creation.icosphere(3, radius=0.03)
    hand.apply_translation([0.08, 0.0, 0.0])
    scene = write_scene(tmp_path / "held_0001", trimesh.creation.box([0.1, 0.1, 0.1]), n_frames=20, extra=hand)
    sequence, annotation = _load(scene)
    bounded = reconstruct_sequence(sequence, annotation, voxel_size=0.004, support_plane=False)
    loose = reconstruct_sequence(sequence, annotation, voxel_size=0.004, support_plane=False, box_prior=False)
    assert loose.extents[0] == pytest.approx(0.1 + 0.015, abs=0.004)  # the hand, out to the grid's edge
    assert bounded.extents[0] == pytest.approx(0.1 * (1 + BOX_BOUND_SLACK / 2), abs=0.004)  # out to the bound: 5 mm
    np.testing.assert_allclose(bounded.extents[1:], [0.1, 0.1], atol=0.004)  # the other sides, untouched


def test_one_thread_gives_the_reconstruction_of_two(box_scene):
    """A batch's unit reconstructs on one thread (ahead=False: no frame decoded and prepared ahead on a second one):
    the same mesh, box, poses and surface labels, bit for bit."""
    sequence, annotation = _load(box_scene)
    two, one = reconstruct_sequence(sequence, annotation, voxel_size=0.004), reconstruct_sequence(sequence, annotation, voxel_size=0.004, ahead=False)
    np.testing.assert_array_equal(one.mesh.vertices, two.mesh.vertices)
    np.testing.assert_array_equal(one.mesh.faces, two.mesh.faces)
    np.testing.assert_array_equal(one.extents, two.extents)
    assert one.poses.keys() == two.poses.keys() and all(np.array_equal(one.poses[f], two.poses[f]) for f in one.poses)
    np.testing.assert_array_equal(one.surface.labels, two.surface.labels)


def test_cup_cavity_is_carved(cup_scene):
    sequence, annotation = _load(cup_scene)
    # 40 frames at 320x240 see into the cavity from a few frames only: carving alone leaves its lower part by the
    # near wall, and says so: that surface is labelled unseen (the fused surface opens it: tests/test_reconstruct_tsdf.py)
    rec = reconstruct_sequence(sequence, annotation, surface="carving")
    mesh = rec.mesh.copy()
    mesh.apply_translation(rec.centre_shift)
    assert 1.2 < mesh.volume / cup_scene.mesh.volume < 2.0
    assert rec.surface.shares["unseen"] > 0.05
    np.testing.assert_allclose(rec.extents, cup_scene.extents, atol=0.003)
    # the evidence hull (an option, the same for any category) drops it: no frame measured a surface there
    hull = reconstruct_sequence(sequence, annotation, evidence_hull=True, surface="carving")
    hull_mesh = hull.mesh.copy()
    hull_mesh.apply_translation(hull.centre_shift)
    assert fscore(hull_mesh, cup_scene.mesh, 0.005) >= 0.98
    assert 0.9 < hull_mesh.volume / cup_scene.mesh.volume < 1.25
    np.testing.assert_allclose(hull.extents, cup_scene.extents, atol=0.003)
    annotation.category = "camera"
    assert reconstruct_sequence(sequence, annotation, evidence_hull=True, surface="carving").mesh.volume == pytest.approx(hull.mesh.volume, rel=1e-6)
    assert reconstruct_sequence(sequence, annotation, surface="carving").mesh.volume == pytest.approx(rec.mesh.volume, rel=1e-6)


def test_symmetry_fills_the_sides_never_seen(tmp_path):
    # a can seen from an eighth of the azimuths only: without symmetry its far side stays uncarved up to the box
    scene = write_scene(tmp_path / "can_0001", y_cylinder(0.03, 0.08), n_frames=24, arc_deg=45, category="can", symmetry="y")
    sequence, annotation = _load(scene)
    rec = reconstruct_sequence(sequence, annotation, frames=[f for f in sequence.ids if int(f) % 2 == 0])
    assert rec.report["frames_used"] == 12
    np.testing.assert_allclose(rec.extents, [0.06, 0.08, 0.06], atol=0.003)
    annotation.symmetry = "none"
    plain = reconstruct_sequence(sequence, annotation, surface="carving")  # the hull alone (fusion makes the seen side tighter)
    true_volume = np.pi * 0.03**2 * 0.08
    assert abs(rec.mesh.volume / true_volume - 1) < 0.1
    # the hull alone keeps its far side out to the annotated box (5 % slack, a voxel of smoothing): the box's corners
    assert plain.mesh.volume / true_volume > 1.05 and 0.062 < plain.extents[0] <= 0.06 * 1.05 + 0.002


def test_frame_subset_and_bad_inputs(box_scene, tmp_path):
    sequence, annotation = _load(box_scene)
    with pytest.raises(InputError, match="no pose"):
        reconstruct_sequence(sequence, annotation, frames=["9999999"])
    with pytest.raises(InputError, match="voxel size"):
        reconstruct_sequence(sequence, annotation, voxel_size=-1.0)
    empty = annotation.copy()
    empty.frames = {}
    with pytest.raises(InputError, match="no frame"):
        reconstruct_sequence(sequence, empty)
    # poses pointing away from the object: everything is carved or nothing seen -> a clear error, not a crash
    wrong = annotation.copy()
    for pose in wrong.frames.values():
        pose.position = pose.position + np.array([0.0, 0.0, -0.3])  # object put 0.3 m in front of the wall it is on
    with pytest.raises(InputError, match="carving left no object"):
        reconstruct_sequence(sequence, wrong)


@pytest.fixture(scope="module")
def synthetic_mug(tmp_path_factory):
    """A 100-frame synthetic held mug (sequences.synth) reconstructed from poses off by up to 1 deg / 2 mm."""
    synth = pytest.importorskip("sequences.synth")
    # 100 frames: the generator holds the object in ~30-frame grasps; with 40 frames (two grasps)
    # the hand and arm stay in the views of one grasp only and are not carved (measured +25 mm)
    root = synth.generate_sequence(tmp_path_factory.mktemp("synth") / "mug_synth", "mug", frames=100, seed=2)
    truth = synth.load_truth(root)
    annotation = synth.truth_annotation(truth, truth.ids, rotation_deg=1.0, translation_m=0.002, extents_rel=0.1, seed=0)
    rec = reconstruct_sequence(open_sequence(root), annotation)
    mesh = rec.mesh.copy()
    mesh.apply_translation(rec.centre_shift)
    return truth, rec, mesh


@pytest.mark.slow  # generates a 100-frame synthetic sequence (~30-50 s on a loaded 2-core machine)
def test_synthetic_held_mug_surface(synthetic_mug):
    truth, rec, mesh = synthetic_mug
    assert rec.mesh.is_watertight
    assert fscore(mesh, truth.mesh, 0.005) >= 0.9
    # the lower inside by the near wall is never seen free: carving keeps it (F@1cm 0.979 measured), labelled
    # unseen; the evidence hull, an option, drops it (no frame saw a surface there)
    assert fscore(mesh, truth.mesh, 0.01) >= 0.97 and rec.surface.shares["unseen"] > 0.03
    root = truth.root
    annotation = load_annotation(root / "annotation.yaml") if (root / "annotation.yaml").exists() else None
    if annotation is None:
        from sequences.synth import truth_annotation

        annotation = truth_annotation(truth, truth.ids, rotation_deg=1.0, translation_m=0.002, extents_rel=0.1, seed=0)
    hull = reconstruct_sequence(open_sequence(root), annotation, evidence_hull=True)
    hull_mesh = hull.mesh.copy()
    hull_mesh.apply_translation(hull.centre_shift)
    assert fscore(hull_mesh, truth.mesh, 0.01) >= 0.98


@pytest.mark.slow  # the palm's patch by the handle is seen free only through projector shadows (carve(shadows=True))
def test_synthetic_held_mug_box_and_no_hand_remnants(synthetic_mug):
    truth, rec, mesh = synthetic_mug
    from scipy.spatial import cKDTree

    tree = cKDTree(trimesh.sample.sample_surface(truth.mesh, 50000, seed=1)[0])
    distance = tree.query(mesh.vertices)[0]
    # nothing the frames measured lies farther than 1 cm from the true surface: no hand remnant; what does (the
    # mug's lower inside, never seen free) is labelled unseen
    from reconstruct.seen import UNSEEN

    # (the unseen inside's edge, within the 4 mm tolerance of the measured inner wall, counts as observed: 4 % measured)
    far = distance > 0.01
    assert far.any() and np.mean(rec.surface.labels[far] == UNSEEN) > 0.94
    np.testing.assert_allclose(rec.extents, truth.extents, atol=0.003)
