"""Dataset readers: REDWOOD75-format ground truth, NOCS REAL275 samples and BOP datasets, as lists of :class:`Sample`."""

from __future__ import annotations

from pathlib import Path

from sequences.errors import InputError

from .base import Dataset
from .sample import Sample


def open_dataset(root: str | Path, frames: str | Path | None = None) -> Dataset:
    """Open a dataset folder: NOCS when it holds ``gts/``, BOP when it holds ``models/models_info.json``, else
    REDWOOD75 format when it holds ``annotations.json`` (our BOP and NOCS exports hold one too: their index)."""
    root = Path(root)
    if (root / "gts").is_dir():
        from .nocs import NocsDataset

        if frames is not None:
            raise InputError(frames, "--frames does not apply to a NOCS dataset (its frames are inside it)")
        return NocsDataset(root)
    if (root / "models" / "models_info.json").is_file():
        from .bop import BopDataset

        if frames is not None:
            raise InputError(frames, "--frames does not apply to a BOP dataset (its frames are inside it)")
        return BopDataset(root)
    if (root / "annotations.json").is_file():
        from .redwood75 import Redwood75Dataset

        return Redwood75Dataset(root, frames)
    if not root.is_dir():
        raise InputError(root, "dataset folder not found")
    raise InputError(root, "not a dataset folder (expected annotations.json, REDWOOD75 format, a NOCS gts/ folder or BOP's models/models_info.json)")


__all__ = ["Dataset", "Sample", "open_dataset"]
