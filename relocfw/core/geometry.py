"""Rotations, rigid transforms and pose errors. Quaternions are (w, x, y, z).

The conversions are scipy's (`scipy.spatial.transform.Rotation`, whose quaternions
are (x, y, z, w): `scipy_order` and `w_first` reorder them); `mean_quaternion` is
the one rotation mean of relocfw, the one scipy computes, over batches.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from relocfw.core.errors import DataError
from relocfw.core.values import Pose

RIGID_TOLERANCE = 1e-2  # KinectFusion poses drift from orthonormal by ~1e-4; 1e-2 is clearly broken


def scipy_order(quaternions: np.ndarray) -> np.ndarray:
    """(w, x, y, z) -> scipy's (x, y, z, w), along the last axis (`scalar_first=` needs
    scipy 1.14; relocfw supports 1.10)."""
    return np.roll(np.asarray(quaternions, dtype=np.float64), -1, axis=-1)


def w_first(quaternions: np.ndarray) -> np.ndarray:
    """scipy's (x, y, z, w) -> (w, x, y, z), along the last axis."""
    return np.roll(np.asarray(quaternions, dtype=np.float64), 1, axis=-1)


def quaternion_to_matrix(quaternion: np.ndarray) -> np.ndarray:
    """Rotation matrix of a (not necessarily unit) quaternion, w first."""
    return Rotation.from_quat(scipy_order(quaternion)).as_matrix()


def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (w first, w >= 0) of a rotation matrix.

    Picks the largest of w, x, y, z to divide by, so the result stays accurate near
    180-degree rotations where the trace formula loses all precision. Kept by hand, not
    scipy's Rotation.from_matrix: scipy first snaps a drifted matrix to the nearest
    rotation, which moves ground-truth quaternions by ~1e-9 (synthetic) to ~1e-4
    (KinectFusion), enough to change a trained model (measured on the default command's
    demo model); these are the quaternions every model so far was trained on.
    """
    m = np.asarray(rotation, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = (trace, m[0, 0], m[1, 1], m[2, 2])
    largest = int(np.argmax(candidates))
    if largest == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif largest == 1:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif largest == 2:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation matrix nearest to a 3x3 `matrix` (orthogonal Procrustes, by SVD)."""
    u, _, vt = np.linalg.svd(np.asarray(matrix, dtype=np.float64))
    if np.linalg.det(u @ vt) < 0:  # the nearest orthogonal matrix is a reflection
        u[:, -1] = -u[:, -1]
    return u @ vt


def pose_from_matrix(matrix: np.ndarray, source: str = "pose") -> Pose:
    """Pose of a 4x4 camera-to-world matrix, refusing anything that is not rigid.

    Args:
        matrix: 4x4 homogeneous transform.
        source: what to name in the error message (usually the file).
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise DataError(f"{source}: expected a 4x4 matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise DataError(f"{source}: pose contains NaN or infinity")
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
        raise DataError(f"{source}: last row must be 0 0 0 1, got {m[3].tolist()}")
    rotation = m[:3, :3]
    deviation = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if deviation > RIGID_TOLERANCE:
        raise DataError(
            f"{source}: not a rigid transform (rotation is not orthonormal: "
            f"max |R^T R - I| = {deviation:.3g} > {RIGID_TOLERANCE})"
        )
    if np.linalg.det(rotation) < 0:
        raise DataError(f"{source}: not a rigid transform (rotation is a reflection, det < 0)")
    return Pose(m[:3, 3], matrix_to_quaternion(rotation))


def pose_to_matrix(pose: Pose) -> np.ndarray:
    """4x4 camera-to-world matrix of a pose."""
    m = np.eye(4)
    m[:3, :3] = quaternion_to_matrix(pose.quaternion)
    m[:3, 3] = pose.position
    return m


def position_error(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Euclidean distance in metres, row-wise for [N, 3] inputs."""
    return np.linalg.norm(np.asarray(estimate) - np.asarray(truth), axis=-1)


def orientation_error_deg(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Angle between rotations, 2 * acos(|<q1, q2>|) in degrees, row-wise.

    The absolute value makes q and -q (the same rotation) zero apart.
    """
    q1 = np.asarray(estimate, dtype=np.float64)
    q2 = np.asarray(truth, dtype=np.float64)
    q1 = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    q2 = q2 / np.linalg.norm(q2, axis=-1, keepdims=True)
    dot = np.clip(np.abs(np.sum(q1 * q2, axis=-1)), 0.0, 1.0)
    return np.degrees(2.0 * np.arccos(dot))


def mean_quaternion(quaternions: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """(Weighted) average rotation of [..., N, 4] quaternions (w first) -> [..., 4],
    indifferent to the inputs' signs, on one hemisphere (as `on_one_hemisphere`).

    The chordal L2 mean, as scipy's `Rotation.mean` computes it: the principal
    eigenvector of sum(w q q^T) over the unit quaternions (Markley et al. 2007), the
    rotation closest to all inputs in the chordal sense; q and -q add the same term.
    Written out rather than called because it runs over leading batch axes in one
    call (Monte Carlo samples of a batch, relocfw.core.sampling.mean_quaternions),
    which scipy's mean does (`axis=`) only in releases far newer than relocfw's floor
    of scipy 1.10; a loop of scipy calls is about ten times slower at 16 images.

    Args:
        quaternions: [..., N, 4], not necessarily unit.
        weights: [N] or [..., N] non-negative weights; None weighs all alike.
    """
    q = np.asarray(quaternions, dtype=np.float64)
    q = q / np.sqrt((q * q).sum(axis=-1, keepdims=True))
    weighted = q if weights is None else q * np.asarray(weights, dtype=np.float64)[..., None]
    _, vectors = np.linalg.eigh(np.swapaxes(weighted, -1, -2) @ q)
    return rows_on_one_hemisphere(vectors[..., -1])


def rows_on_one_hemisphere(quaternions: np.ndarray) -> np.ndarray:
    """`on_one_hemisphere` of every [..., 4] row: each row or its negation, whichever
    has a positive first non-zero component (w > 0 where w is not zero)."""
    q = np.asarray(quaternions, dtype=np.float64)
    lead = q[..., 0]
    if np.any(lead == 0):  # rare: decide by the first non-zero component instead
        lead = np.take_along_axis(q, np.argmax(q != 0, axis=-1)[..., None], axis=-1)[..., 0]
    return np.where((lead < 0)[..., None], -q, q)


QUATERNION_TOLERANCE = 1e-3  # |1 - |q|| above this is reported, not silently fixed
QUATERNION_MINIMUM = 1e-6  # a norm this small has no direction to normalise to


def checked_quaternion(values: Sequence[float], source: str) -> np.ndarray:
    """A unit quaternion from file values, following one documented rule.

    Non-finite values and near-zero norms are refused; a norm off by more than
    QUATERNION_TOLERANCE is normalised with a warning naming `source`; smaller
    rounding is normalised silently.
    """
    q = np.asarray(values, dtype=np.float64)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise DataError(f"{source}: quaternion must be 4 finite numbers, got {list(values)}")
    norm = float(np.linalg.norm(q))
    if norm < QUATERNION_MINIMUM:
        raise DataError(f"{source}: quaternion has (near) zero norm {norm:.3g}")
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        warnings.warn(f"{source}: quaternion norm {norm:.6g}, normalised", stacklevel=2)
    return q / norm


def conjugate(quaternion: np.ndarray) -> np.ndarray:
    """The inverse rotation of a unit quaternion (w, x, y, z)."""
    w, x, y, z = quaternion
    return np.array([w, -x, -y, -z])
