import numpy as np
import pytest
import torch

from relocfw.geometry import mean_quaternion, orientation_error_deg
from relocfw.plugins.posenet import PoseNet
from relocfw.pose_head import PoseHead, mean_quaternions


def axis_angle(axis, degrees):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    half = np.radians(degrees) / 2
    return np.array([np.cos(half), *(np.sin(half) * axis)])


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


def test_mc_dropout_gives_mean_pose_and_spread():
    torch.manual_seed(0)
    head = PoseHead(in_features=16, feature_dim=64, dropout=0.5).eval()
    pooled = torch.rand(5, 16)
    deterministic = head(pooled, lambda p: p)
    sampled = head(pooled, lambda p: p, mc_samples=200)
    assert deterministic.position_spread is None
    assert sampled.position_spread.shape == (5,) and torch.all(sampled.position_spread > 0)
    assert sampled.orientation_spread_deg.shape == (5,)
    # The descriptor does not depend on dropout: crop search is unchanged by sampling.
    assert torch.equal(sampled.features, deterministic.features)
    # With many samples the mean pose approaches the dropout-free pose.
    assert torch.allclose(sampled.positions, deterministic.positions, atol=0.1)
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
