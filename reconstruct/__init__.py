"""From posed frames to ground truth: carving, meshing, smoothing, tight box, masks, REDWOOD75 export.

The choice of surface lives here, not in :mod:`reconstruct.pipeline`: the command line reads it without importing
the pipeline (NumPy, trimesh, Open3D), so that a batch's local processes start while the command is still importing.
"""

#: The surface meshed: ``carving`` (the carved occupancy) or ``tsdf`` (the depth fused where frames measured it, the
#: carved hull elsewhere: :mod:`reconstruct.tsdf`). Measured on the benchmark's dev split from the true poses (19
#: sequences): the largest error of a measured box face 1.7 -> 1.2 mm at the median (mean 2.0 -> 1.6; the square bowl's
#: 3.4 -> 2.9 mm meets the goal, the laptop's 5.4 -> 4.4 does not), observed precision and recall at 5 mm unchanged
#: but for the laptop (0.95 / 0.92 -> 0.97 / 0.94) and a can (precision 0.936 -> 0.929), the sum of posed F@5mm
#: 18.56 -> 18.60; fusion costs ~25 % more CPU (laptop, the largest object: 9.0 -> 11.5 s for 100 frames).
SURFACES = ("carving", "tsdf")
SURFACE = "tsdf"
