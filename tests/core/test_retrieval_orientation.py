"""refine=retrieval with k >= 2: the orientation of the answer, computed by hand.

Rotations about one axis have a closed-form weighted chordal mean: the rotation by the
angle of the weighted sum of the unit vectors (cos t_i, sin t_i), atan2(sum w_i sin t_i,
sum w_i cos t_i), about that axis (the principal eigenvector of sum w_i q_i q_i^T lies
in the plane of (1, 0) and the axis, at half that angle). So the expected answers below
need neither relocfw nor scipy.
"""

import numpy as np
import pytest

from relocfw import MapImage, RefineQuery
from relocfw.core.geometry import orientation_error_deg
from relocfw.core.values import Pose
from relocfw.plugins.retrieval_refiner import RetrievalRefiner
from tests.rotations import axis_angle

AXIS = np.array([1.0, 2.0, 2.0]) / 3.0  # a unit axis off every coordinate axis
# One-number descriptors; a query at 1.0 is 1, 2, 5 and 99 from them. The z-score
# divides every distance by the same spread, so the inverse-distance weights keep the
# ratios 1 : 1/2 : 1/5 (up to the 1e-6 guard, ~1e-4 of a weight here).
DESCRIPTORS = np.array([[0.0], [3.0], [-4.0], [100.0]])
QUERY = np.array([1.0])
POSITIONS = np.array([[0.0, 0, 0], [3.0, 0, 0], [0.0, 17.0, 0], [50.0, 50.0, 50.0]])
WEIGHTS = {2: (2 / 3, 1 / 3), 3: (10 / 17, 5 / 17, 2 / 17)}  # 1 : 1/2 (: 1/5), normalised
EXPECTED_POSITIONS = {2: [1.0, 0.0, 0.0], 3: [15 / 17, 2.0, 0.0]}


def one_axis_mean(weights: np.ndarray, degrees: tuple[float, ...]) -> float:
    """The weighted chordal mean of rotations about one axis, in degrees (module)."""
    radians = np.radians(degrees[: len(weights)])
    return float(np.degrees(np.arctan2(weights @ np.sin(radians), weights @ np.cos(radians))))


def refined(k: int, degrees: tuple[float, ...]) -> Pose:
    """The refiner's answer for the query when the map images are turned by `degrees`
    about AXIS (one angle per map image, nearest the query first)."""
    views = [
        MapImage(f"map {i}", np.zeros((4, 4, 3), np.uint8), Pose(p, axis_angle(AXIS, angle)))
        for i, (p, angle) in enumerate(zip(POSITIONS, degrees, strict=True))
    ]
    refiner = RetrievalRefiner(k=k)
    refiner.fit(views, DESCRIPTORS)
    identity = Pose(np.zeros(3), [1.0, 0, 0, 0])
    return refiner.refine(RefineQuery(np.zeros((4, 4, 3), np.uint8), identity, QUERY)).pose


@pytest.mark.parametrize("k", [2, 3])
@pytest.mark.parametrize(
    "degrees",
    [
        # k=2: atan2(1/3, 2/3) = 26.57 degrees; k=3: atan2(5, 10 - 2) = 32.01 degrees.
        (0.0, 90.0, 180.0, 45.0),
        # Around the half turn, where the map's quaternions (kept at w > 0, as every
        # Pose keeps them) of rotations 20 degrees apart point nearly opposite ways: a
        # mean that adds quaternions without aligning their signs turns tens of degrees
        # away. k=2: 176.64 degrees; k=3: 179.37.
        (170.0, -170.0, -160.0, 45.0),
    ],
    ids=["quarter-turns", "around-the-half-turn"],
)
def test_k_nearest_orientations_average_by_their_weights(k, degrees):
    pose = refined(k, degrees)
    np.testing.assert_allclose(pose.position, EXPECTED_POSITIONS[k], atol=1e-3)
    expected = axis_angle(AXIS, one_axis_mean(np.array(WEIGHTS[k]), degrees))
    assert orientation_error_deg(pose.quaternion, expected) < 1e-2
    assert pose.quaternion[0] >= 0  # one hemisphere, as every relocfw quaternion
