from typing import NamedTuple

import numpy as np
import pytest
import torch

from relocfw.core.geometry import mean_quaternion, orientation_error_deg
from relocfw.core.sampling import mean_quaternions
from relocfw.core.values import PoseOutput
from relocfw.model.pose_head import PoseHead
from relocfw.plugins.posenet import PoseNet
from tests.rotations import axis_angle


def test_batched_quaternion_mean_ignores_sign_flips():
    base = axis_angle([1, 2, 0.5], 40)
    samples = np.stack([axis_angle([1, 2, 0.5], 40 + d) for d in (-6, -2, 2, 6)])
    samples[[1, 3]] *= -1  # the same rotations, written with the other sign
    plain_mean = samples.mean(0)
    assert orientation_error_deg(plain_mean, base) > 10  # what a naive mean gets wrong
    mean = mean_quaternions(torch.tensor(samples[:, None], dtype=torch.float64))[0].numpy()
    assert orientation_error_deg(mean, base) < 1e-4
    assert mean[0] >= 0


def test_weighted_mean_quaternion_leans_to_the_heavier_rotation():
    a, b = axis_angle([0, 0, 1], 0), axis_angle([0, 0, 1], 60)
    mean = mean_quaternion(np.stack([a, -b]), weights=np.array([3.0, 1.0]))
    assert orientation_error_deg(mean, a) < orientation_error_deg(mean, b)


class Sampled(NamedTuple):
    head: PoseHead
    pooled: torch.Tensor  # [5, 16] head inputs
    sampled: PoseOutput  # the MC-dropout answer
    plain: PoseOutput  # the dropout-free answer
    dropped: torch.Tensor  # [samples * 5, 64] the descriptors after the drawn masks


@torch.no_grad()
def sampled_head(monkeypatch, samples: int) -> Sampled:
    """A seeded head's MC-dropout answer for 5 inputs, with the dropped features it used.

    torch's dropout is wrapped to record what it returned, so a test can recompute the
    answer from the very masks the head drew, without touching its random stream.
    """
    torch.manual_seed(0)
    head = PoseHead(in_features=16, feature_dim=64, dropout=0.5).eval()
    pooled = torch.rand(5, 16)
    recorded = []
    dropout = torch.nn.functional.dropout

    def recording(x, p=0.5, training=True, inplace=False):
        out = dropout(x, p, training, inplace)
        recorded.append(out.clone())
        return out

    monkeypatch.setattr(torch.nn.functional, "dropout", recording)
    # An affine to-world map: samples must be mapped before they are averaged.
    sampled = head(pooled, lambda p: 3.0 * p + 1.0, mc_samples=samples)
    monkeypatch.undo()
    assert len(recorded) == 1, "expected one dropout call drawing every mask"
    plain = head(pooled, lambda p: 3.0 * p + 1.0)
    return Sampled(head, pooled, sampled, plain, recorded[0])


def as_array(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().double().numpy()


def test_mc_dropout_answer_is_the_mean_and_spread_of_the_sampled_poses(monkeypatch):
    head, _, sampled, _, dropped = sampled_head(monkeypatch, samples=200)
    dropped = dropped.double().numpy()
    assert dropped.shape == (200 * 5, 64)
    # Recomputed in float64 numpy from the regressor's weights and the recorded masks.
    position, orientation = head.regressor.position, head.regressor.orientation
    positions = dropped @ as_array(position.weight).T + as_array(position.bias)
    positions = (3.0 * positions + 1.0).reshape(200, 5, 3)
    quaternions = dropped @ as_array(orientation.weight).T + as_array(orientation.bias)
    quaternions = quaternions.reshape(200, 5, 4)
    mean_position = positions.mean(axis=0)
    spread = np.sqrt(((positions - mean_position) ** 2).sum(axis=2).mean(axis=0))
    means = np.stack([mean_quaternion(quaternions[:, b]) for b in range(5)])
    angles = np.stack([orientation_error_deg(quaternions[:, b], means[b]) for b in range(5)])
    # Values are 0.2-2 m, spreads about 0.7 m and several degrees; the tolerances
    # are float32 rounding, five or more orders of magnitude below them.
    assert np.abs(mean_position).min() > 0.1 and spread.min() > 0.1 and angles.mean() > 1
    assert np.allclose(sampled.positions.numpy(), mean_position, rtol=1e-5, atol=1e-6)
    assert np.allclose(sampled.position_spread.numpy(), spread, rtol=1e-5, atol=1e-6)
    assert orientation_error_deg(sampled.quaternions.numpy(), means).max() < 1e-2
    assert np.allclose(sampled.orientation_spread_deg.numpy(), angles.mean(axis=1), rtol=1e-4)


def test_mc_dropout_masks_drop_about_half_and_rescale_the_rest(monkeypatch):
    head, pooled, _, _, dropped = sampled_head(monkeypatch, samples=200)
    dropped = dropped.view(200, 5, 64)
    features = head.describe(pooled).expand_as(dropped)
    kept = dropped != 0
    assert torch.allclose(dropped[kept], 2.0 * features[kept])  # scaled by 1 / (1 - 0.5)
    live = features != 0  # ReLU zeros stay zero whatever the mask
    assert abs(kept[live].float().mean().item() - 0.5) < 0.02
    # Every sample draws its own mask: no two of the 200 are the same.
    assert len({tuple(row.tolist()) for row in kept[:, 0]}) == 200


def test_mc_dropout_mean_pose_converges_to_the_dropout_free_pose(monkeypatch):
    # Dropout rescales what it keeps, so the expected dropped descriptor is the
    # descriptor and the linear regressor's expected position is the plain one. The
    # mean of N samples is off by about spread / sqrt(N) per axis; allow four times that.
    _, _, sampled, plain, _ = sampled_head(monkeypatch, samples=40000)
    assert plain.position_spread is None
    assert torch.equal(sampled.features, plain.features)
    error = (sampled.positions - plain.positions).abs()
    allowed = 4 * sampled.position_spread[:, None] / np.sqrt(40000)
    assert torch.all(error < allowed)
    assert torch.all(allowed < 0.02 * plain.positions.norm(dim=1, keepdim=True))
    assert torch.allclose(sampled.quaternions.norm(dim=1), torch.ones(5), atol=1e-5)


def test_more_dropout_means_more_spread():
    torch.manual_seed(0)
    head = PoseHead(in_features=16, feature_dim=64, dropout=0.1).eval()
    pooled = torch.rand(4, 16)
    low = head(pooled, lambda p: p, mc_samples=100).position_spread
    head.dropout_rate = 0.7
    high = head(pooled, lambda p: p, mc_samples=100).position_spread
    assert torch.all(high > low)


def test_mc_samples_is_a_test_time_option():
    model = PoseNet(input_size=32, width=0.125, feature_dim=16, mc_samples=8)
    assert "mc_samples" in model.test_time_options
    assert set(model.state_dict()) == set(
        PoseNet(input_size=32, width=0.125, feature_dim=16).state_dict()
    )
    model.eval()
    out = model(torch.rand(2, 3, 32, 32))
    assert out.position_spread.shape == (2,)
    with pytest.raises(Exception, match="mc_samples"):
        PoseNet(input_size=32, mc_samples=-1)
