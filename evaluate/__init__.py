"""Shared geometry and metrics, dataset readers, the method interface, and evaluation reports."""

#: What a batch's local processes import once (batch.local's server): the methods and the datasets.
PRELOAD = ("numpy", "scipy.spatial", "trimesh", "open3d", "PIL.PngImagePlugin", "PIL.JpegImagePlugin", "evaluate.units", "evaluate.runner", "evaluate.datasets",
           "evaluate.methods.box", "evaluate.methods.template")
