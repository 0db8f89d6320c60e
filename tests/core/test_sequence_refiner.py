"""refine=sequence: the VidLoc-style recurrent model and its query contract."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from relocfw import ConfigError, DataError, MapImage, Pose
from relocfw.core.geometry import mean_quaternion, orientation_error_deg
from relocfw.core.refinement import RefineQuery
from relocfw.model.sequence_network import SequencePoseNetwork
from relocfw.plugins.sequence_refiner import (
    SequenceRefiner,
    pose_loss,
    recording_of,
    recordings_of,
)
from tests.rotations import axis_angle

DIM = 12
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def trajectory(count: int, start: float) -> np.ndarray:
    """[count, 3] a camera moving smoothly along a curve."""
    t = start + np.linspace(0.0, 1.0, count)
    return np.stack([np.cos(2 * t), np.sin(3 * t), 0.3 * t], axis=1)


def descriptors_of(positions: np.ndarray, rng: np.random.Generator, noise: float) -> np.ndarray:
    """Descriptors that encode the position (a fixed random lift) plus noise."""
    lift = np.random.default_rng(7).normal(size=(3, DIM))
    return positions @ lift + noise * rng.normal(size=(len(positions), DIM))


def map_of(recordings: int = 2, frames: int = 40) -> tuple[list[MapImage], np.ndarray]:
    rng = np.random.default_rng(0)
    views, positions = [], []
    for r in range(recordings):
        points = trajectory(frames, start=r * 1.3)
        positions.append(points)
        views += [
            MapImage(f"seq-{r:02d}/frame-{i:06d}", np.zeros((4, 4, 3), np.uint8), Pose(p, IDENTITY))
            for i, p in enumerate(points)
        ]
    return views, descriptors_of(np.concatenate(positions), rng, noise=0.05)


def query(name: str, descriptor: np.ndarray) -> RefineQuery:
    return RefineQuery(
        np.zeros((4, 4, 3), np.uint8), Pose(np.zeros(3), IDENTITY), descriptor, name=name
    )


def fitted(direction: str = "causal", window: int = 4, steps: int = 150, seed: int = 0):
    refiner = SequenceRefiner(window=window, direction=direction, hidden=16, steps=steps, seed=seed)
    refiner.fit(*map_of())
    return refiner


def answers(refiner: SequenceRefiner, names: list[str], descriptors: np.ndarray) -> np.ndarray:
    return np.stack(
        [refiner.refine(query(n, d)).pose.position for n, d in zip(names, descriptors, strict=True)]
    )


def test_the_recording_is_the_folder_part_of_the_name():
    assert recording_of("seq-03/frame-000042") == "seq-03"
    assert recording_of("a/b/frame") == "a/b"
    assert recording_of("frame-000042") == ""
    rows = recordings_of(["s1/a", "s2/a", "s1/b", "s2/b", "s1/c"])
    assert [r.tolist() for r in rows] == [[0, 2, 4], [1, 3]]


@pytest.mark.parametrize("direction, reads_future", [("causal", False), ("bidirectional", True)])
def test_only_the_bidirectional_network_reads_later_frames_of_a_clip(direction, reads_future):
    torch.manual_seed(0)
    network = SequencePoseNetwork(DIM, hidden=8, direction=direction).eval()
    clip = torch.randn(1, 6, DIM)
    perturbed = clip.clone()
    perturbed[0, 4:] += 5.0  # frames after t = 3
    with torch.inference_mode():
        before, _ = network(clip)
        after, _ = network(perturbed)
    assert torch.equal(before[0, :4], after[0, :4]) != reads_future
    assert not torch.allclose(before[0, 4:], after[0, 4:])  # later outputs do read them


@pytest.mark.parametrize("direction", ["causal", "bidirectional"])
def test_a_query_never_reads_a_frame_after_it(direction):
    """The query contract: the answers for frames 0..k are the same whatever follows."""
    refiner = fitted(direction)
    names = [f"seq-09/frame-{i:06d}" for i in range(10)]
    rng = np.random.default_rng(1)
    descriptors = descriptors_of(trajectory(10, 0.4), rng, noise=0.1)
    first = answers(refiner, names, descriptors)
    changed = descriptors.copy()
    changed[6:] += rng.normal(scale=3.0, size=changed[6:].shape)
    second = answers(refiner, names, changed)  # a second pass: the history starts afresh
    np.testing.assert_array_equal(first[:6], second[:6])
    assert not np.allclose(first[6:], second[6:])


def test_the_answer_reads_the_frames_before_it_within_the_window():
    refiner = fitted(window=3)
    names = [f"seq-09/frame-{i:06d}" for i in range(6)]
    descriptors = descriptors_of(trajectory(6, 0.2), np.random.default_rng(2), noise=0.1)
    base = answers(refiner, names, descriptors)
    earlier = descriptors.copy()
    earlier[1] += 3.0  # inside the window of frames 1..3, outside that of 4 and 5
    moved = answers(refiner, names, earlier)
    assert not np.allclose(base[2], moved[2]) and not np.allclose(base[3], moved[3])
    np.testing.assert_allclose(base[4:], moved[4:], atol=1e-6)


def test_recordings_keep_their_own_history_and_a_repeated_query_starts_afresh():
    refiner = fitted()
    rng = np.random.default_rng(3)
    a = descriptors_of(trajectory(5, 0.1), rng, noise=0.1)
    b = descriptors_of(trajectory(5, 1.5), rng, noise=0.1)
    a_names = [f"seq-a/frame-{i}" for i in range(5)]
    b_names = [f"seq-b/frame-{i}" for i in range(5)]
    alone = answers(refiner, a_names, a)
    # Interleaved with another recording, and with the first query asked twice (the
    # untimed warm-up of relocfw.report.evaluation), recording a answers the same.
    refiner.refine(query(a_names[0], a[0]))
    mixed = []
    for i in range(5):
        mixed.append(refiner.refine(query(a_names[i], a[i])).pose.position)
        refiner.refine(query(b_names[i], b[i]))
    np.testing.assert_allclose(np.stack(mixed), alone, atol=1e-6)


def test_it_learns_the_map_and_beats_the_mean_pose_on_new_frames():
    refiner = fitted(steps=400)
    truth = trajectory(20, 0.65)  # between the two map recordings' paths
    descriptors = descriptors_of(truth, np.random.default_rng(4), noise=0.05)
    found = answers(refiner, [f"seq-q/frame-{i:03d}" for i in range(20)], descriptors)
    views, _ = map_of()
    mean = np.mean([v.pose.position for v in views], axis=0)
    error = np.linalg.norm(found - truth, axis=1)
    assert np.median(error) < 0.5 * np.median(np.linalg.norm(truth - mean, axis=1))


def test_a_seed_gives_the_same_model_and_another_seed_another():
    names = [f"seq-q/frame-{i}" for i in range(4)]
    descriptors = descriptors_of(trajectory(4, 0.3), np.random.default_rng(5), noise=0.1)
    state = torch.random.get_rng_state()
    one = answers(fitted(steps=30, seed=1), names, descriptors)
    assert torch.equal(state, torch.random.get_rng_state())  # the caller's stream untouched
    np.testing.assert_array_equal(one, answers(fitted(steps=30, seed=1), names, descriptors))
    assert not np.allclose(one, answers(fitted(steps=30, seed=2), names, descriptors))


def test_bad_options_and_a_query_without_a_name_fail_with_the_key():
    with pytest.raises(ConfigError, match="refine.direction"):
        SequenceRefiner(direction="sideways")
    with pytest.raises(ConfigError, match="refine.window"):
        SequenceRefiner(window=0)
    with pytest.raises(ConfigError, match="not fitted"):
        SequenceRefiner().refine(query("seq/f", np.zeros(DIM)))
    refiner = fitted(steps=5)
    with pytest.raises(ConfigError, match="frame name"):
        refiner.refine(query(None, np.zeros(DIM)))


def test_a_saved_state_answers_as_the_fitted_refiner_and_a_bad_one_names_its_key():
    refiner = fitted(steps=20)
    names = [f"seq-q/frame-{i}" for i in range(5)]
    descriptors = descriptors_of(trajectory(5, 0.3), np.random.default_rng(6), noise=0.1)
    state = refiner.state()
    loaded = SequenceRefiner(window=4, hidden=16)
    loaded.load_state(state)
    np.testing.assert_allclose(
        answers(loaded, names, descriptors), answers(refiner, names, descriptors), atol=1e-6
    )
    with pytest.raises(DataError, match="refine.hidden=32"):
        SequenceRefiner(hidden=32).load_state(state)
    with pytest.raises(DataError, match="position_scale"):
        SequenceRefiner(hidden=16).load_state({**state, "position_scale": torch.tensor(-1.0)})
    with pytest.raises(DataError, match="mean"):
        SequenceRefiner(hidden=16).load_state({k: v for k, v in state.items() if k != "mean"})


def test_a_map_without_frame_names_is_refused_and_reset_forgets_the_history():
    views, descriptors = map_of()
    unnamed = [MapImage(f"map image {i}", v.image, v.pose) for i, v in enumerate(views)]
    with pytest.raises(DataError, match="frame names"):
        SequenceRefiner(steps=1).fit(unnamed, descriptors)
    refiner = fitted(steps=20)
    names = [f"seq-q/frame-{i}" for i in range(3)]
    d = descriptors_of(trajectory(3, 0.2), np.random.default_rng(8), noise=0.1)
    alone = refiner.refine(query("seq-q/frame-9", d[2])).pose.position
    refiner.reset()
    answers(refiner, names[:2], d[:2])
    after_history = refiner.refine(query("seq-q/frame-9", d[2])).pose.position
    refiner.reset()
    np.testing.assert_allclose(refiner.refine(query("seq-q/frame-9", d[2])).pose.position, alone)
    assert not np.allclose(after_history, alone)


# --- orientation: non-identity rotations whose answer is known by hand ---------------

TURN_AXIS = np.array([0.0, 0.6, 0.8])


def heading(t: np.ndarray) -> np.ndarray:
    """Degrees about TURN_AXIS along the curve: 40 to 140, away from 0 and 180, where
    a rotation and its inverse (conjugate) are far apart."""
    return 90.0 + 50.0 * np.sin(2 * t)


def turned_map(recordings: int = 2, frames: int = 40) -> tuple[list[MapImage], np.ndarray]:
    """map_of's recordings, the camera turning smoothly as it moves."""
    views, descriptors = map_of(recordings, frames)
    times = np.concatenate([r * 1.3 + np.linspace(0.0, 1.0, frames) for r in range(recordings)])
    turned = [
        MapImage(v.name, v.image, Pose(v.pose.position, axis_angle(TURN_AXIS, heading(t))))
        for v, t in zip(views, times, strict=True)
    ]
    return turned, descriptors


def test_the_loss_is_indifferent_to_the_quaternions_sign():
    # Row 0: 3-4-5 m off, its quaternion the truth negated (the same rotation): 5 + 0.
    # Row 1: on the spot, identity against a 60 degree turn given as -q: the chord
    # between unit quaternions a half angle of 30 degrees apart, 2 sin(15 deg), x beta 2.
    turn = axis_angle(TURN_AXIS, 60.0)
    positions = torch.tensor([[[3.0, 4.0, 0.0]], [[0.0, 0.0, 0.0]]], dtype=torch.float64)
    quaternions = torch.from_numpy(np.array([[-turn], [IDENTITY]]))
    true_positions = torch.zeros(2, 1, 3, dtype=torch.float64)
    true_quaternions = torch.from_numpy(np.array([[turn], [-turn]]))
    loss = pose_loss(positions, quaternions, true_positions, true_quaternions, beta=2.0)
    expected = (5.0 + 2.0 * 2.0 * np.sin(np.radians(15.0))) / 2
    assert loss.item() == pytest.approx(expected, rel=1e-12)


class TurningNetwork(torch.nn.Module):
    """A stand-in for the trained network: at step t of any clip, position (t, 0, 0)
    and the rotation by 20 + 10 t degrees about TURN_AXIS (w first)."""

    def forward(self, descriptors: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        batch, steps = descriptors.shape[:2]
        turns = [axis_angle(TURN_AXIS, 20.0 + 10.0 * t) for t in range(steps)]
        quaternions = torch.tensor(np.array(turns), dtype=torch.float32).expand(batch, -1, -1)
        positions = torch.zeros(batch, steps, 3)
        positions[..., 0] = torch.arange(steps, dtype=torch.float32)
        return positions, quaternions


def test_the_answer_is_the_last_step_s_orientation_as_the_network_gives_it():
    # With window 4 the k-th query of a recording runs min(k, 4) steps, so its answer
    # turns by 20, 30, 40, 50, 50, 50 degrees: the last step's rotation, unchanged.
    refiner = fitted(window=4, steps=5)
    refiner.network = TurningNetwork()
    names = [f"seq-q/frame-{i}" for i in range(6)]
    descriptors = descriptors_of(trajectory(6, 0.3), np.random.default_rng(9), noise=0.1)
    found = [refiner.refine(query(n, d)).pose for n, d in zip(names, descriptors, strict=True)]
    for pose, degrees in zip(found, [20, 30, 40, 50, 50, 50], strict=True):
        assert orientation_error_deg(pose.quaternion, axis_angle(TURN_AXIS, degrees)) < 1e-4
    steps = np.array([0, 1, 2, 3, 3, 3]) * refiner.position_scale + refiner.position_mean[0]
    np.testing.assert_allclose([p.position[0] for p in found], steps, rtol=1e-6)


def test_it_learns_the_map_s_turning_orientation_and_beats_the_mean_rotation():
    views, descriptors = turned_map()
    refiner = SequenceRefiner(window=4, hidden=16, steps=400, seed=0)
    refiner.fit(views, descriptors)
    times = 0.65 + np.linspace(0.0, 1.0, 20)  # between the two map recordings' paths
    truth = np.array([axis_angle(TURN_AXIS, h) for h in heading(times)])
    descriptors = descriptors_of(trajectory(20, 0.65), np.random.default_rng(4), noise=0.05)
    names = [f"seq-q/frame-{i:03d}" for i in range(20)]
    found = [
        refiner.refine(query(n, d)).pose.quaternion for n, d in zip(names, descriptors, strict=True)
    ]
    error = orientation_error_deg(found, truth)
    mean = mean_quaternion(np.stack([v.pose.quaternion for v in views]))
    # Measured: median 5.7 degrees against the mean rotation's 28; the map's rotations
    # handed to the network conjugated (world-to-camera) give 129, in scipy's order 94.
    assert np.median(error) < 0.5 * np.median(orientation_error_deg(mean[None], truth))
