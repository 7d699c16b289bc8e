"""Each category's typical box: the size a new box gets before a person or a fit sizes it.

Full side lengths (m) along object x, y (up), z (front: a mug's handle side is -z), ShapeNet axes as the annotation
document's. A default only: the category sets this size and nothing else (no code path depends on it); the
annotator's sizing, the outline drag and the reconstruction's tight box replace it.

Where the figures come from (rounded to 5 mm): the median per category of REDWOOD75's boxes
(``../shared/data/redwood75/annotations.json``, raw axes mapped to ShapeNet's) and NOCS REAL275's models' sizes
(``../shared/data/nocs_real_sample/obj_models/*/*_norm.txt``, NOCS axes mapped to ShapeNet's): mugs 7, bottles 6,
bowls 8, cans 2, one camera, one laptop. ``other``: a 10 cm cube.
"""

from __future__ import annotations

import numpy as np

#: category -> full extents (x, y, z) in metres, ShapeNet axes
TYPICAL_EXTENTS: dict[str, tuple[float, float, float]] = {
    "bottle": (0.080, 0.225, 0.080),
    "bowl": (0.155, 0.070, 0.155),
    "mug": (0.090, 0.105, 0.130),
    "can": (0.070, 0.150, 0.070),
    "camera": (0.150, 0.105, 0.180),
    "laptop": (0.280, 0.170, 0.305),
    "other": (0.100, 0.100, 0.100),
}


def typical_extents(category: str) -> np.ndarray:
    """The typical full extents (3,) m of ``category`` (``other``'s for a category the table lacks)."""
    return np.array(TYPICAL_EXTENTS.get(category, TYPICAL_EXTENTS["other"]), dtype=np.float64)
