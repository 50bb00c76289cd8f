"""Array aliases used in signatures. Shapes and units go in docstrings."""
from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ['Floats', 'Bools', 'Ints', 'Pose', 'Poses', 'Vec3', 'Quat']

Floats = NDArray[np.float64]
Bools = NDArray[np.bool_]
Ints = NDArray[np.integer[Any]]   # indices, counts, `Status` codes (any integer width)
Pose = NDArray[np.float64]    # (4, 4) homogeneous, a_from_b, metres
Poses = NDArray[np.float64]   # (n, 4, 4)
Vec3 = NDArray[np.float64]    # (3,)
Quat = NDArray[np.float64]    # (4,) x, y, z, w (ROS order), w >= 0
