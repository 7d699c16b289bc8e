"""The depth noise of a PrimeSense-like structured-light sensor: one model, used where noise is added (the synthetic
sensor, ``sequences.synth.sensor``) and where it is tolerated (the carving, ``reconstruct.carving``).

Axial noise grows with the square of the distance beyond 0.4 m: sigma(z) = 1.2 mm + 1.9 mm (z / m - 0.4)^2, the fit
of Nguyen, Izadi and Lovell (2012, "Modeling Kinect sensor noise", 3DIMPVT) to Kinect v1 depth: 1.2 mm at 0.4 m,
3.1 mm at 1.4 m.
"""

from __future__ import annotations

import numpy as np

#: Noise (m) at the nearest modelled depth, and its growth (m per m^2) beyond that depth (m).
SIGMA_NEAR, SIGMA_GROWTH, NEAR_DEPTH = 0.0012, 0.0019, 0.4


def depth_sigma(z: np.ndarray | float) -> np.ndarray | float:
    """Axial depth noise (standard deviation, metres) at depth ``z`` (metres); an array keeps its dtype."""
    return SIGMA_NEAR + SIGMA_GROWTH * (np.asarray(z) - NEAR_DEPTH) ** 2
