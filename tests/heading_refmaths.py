"""Independent reference maths for the heading fuser's pin tests (scipy's rotations; quaternions (w, x, y, z),
body → ENU): the three step-pin files check the filter's own helpers against these."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def rmat(q) -> np.ndarray:
    return Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()


def qof(R) -> tuple:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return (w, x, y, z)


def rexp(v) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(v, float)).as_matrix()


def cross_mat(v) -> np.ndarray:
    """[v]× built from the cross product itself."""
    return np.column_stack([np.cross(v, e) for e in np.eye(3)])
