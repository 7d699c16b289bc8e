"""From posed frames to ground truth: carving, meshing, smoothing, tight box, masks, REDWOOD75 export.

The choice of surface lives here, not in :mod:`reconstruct.pipeline`: the command line reads it without importing
the pipeline (NumPy, trimesh, Open3D), so that a batch's local processes start while the command is still importing.
"""

#: The surface meshed: ``carving`` (the carved occupancy) or ``tsdf`` (the depth fused where frames measured it, the
#: carved hull elsewhere: :mod:`reconstruct.tsdf`). Fusion places the faces a camera saw more accurately than the
#: hull does, for about a quarter more CPU (docs/reconstruction.md has the figures).
SURFACES = ("carving", "tsdf")
SURFACE = "tsdf"
