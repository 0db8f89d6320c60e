import os
import time

import numpy as np
import pytest
import torch

import relocfw.model.training as training
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.pipeline import Relocalizer
from relocfw.core.values import Pose, PoseOutput
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.model.checkpoints import load_checkpoint
from relocfw.model.loss import FixedWeighting, LearnedWeighting, head_errors, posenet_loss
from relocfw.model.training import TrainingImages, TrainSettings, train_backbone
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.posenet import PoseNet


def test_fixed_loss_is_position_error_plus_beta_quaternion_error():
    positions = torch.tensor([[3.0, 4.0, 0.0]])
    quaternions = torch.tensor([[2.0, 0.0, 0.0, 0.0]])  # normalised to (1, 0, 0, 0)
    true_q = torch.tensor([[0.0, 1.0, 0.0, 0.0]])
    errors = head_errors(positions, quaternions, torch.zeros(1, 3), true_q)
    assert FixedWeighting(10.0)(*errors).item() == pytest.approx(5.0 + 10.0 * np.sqrt(2.0))


def test_auxiliary_heads_are_weighted():
    zero_p, unit_q = torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]])
    off_p = torch.tensor([[1.0, 0, 0]])
    output = PoseOutput(zero_p, unit_q, torch.zeros(1, 2), ((off_p, unit_q), (2 * off_p, unit_q)))
    loss = posenet_loss(output, zero_p, unit_q, FixedWeighting(1.0), auxiliary_weights=(0.3, 0.3))
    assert loss.item() == pytest.approx(0.3 * 1 + 0.3 * 2)


def test_learned_weighting_formula_and_its_optimum():
    weighting = LearnedWeighting(s_position=0.5, s_orientation=-1.0)
    value = weighting(torch.tensor(2.0), torch.tensor(0.1))
    expected = 2.0 * np.exp(-0.5) + 0.5 + 0.1 * np.exp(1.0) - 1.0
    assert value.item() == pytest.approx(expected)
    # Minimising over s gives s = log(error): each task is weighted by 1 / its error.
    optimiser = torch.optim.Adam(weighting.parameters(), lr=0.05)
    for _ in range(800):
        optimiser.zero_grad()
        weighting(torch.tensor(2.0), torch.tensor(0.1)).backward()
        optimiser.step()
    assert weighting.s_position.item() == pytest.approx(np.log(2.0), abs=0.02)
    assert weighting.s_orientation.item() == pytest.approx(np.log(0.1), abs=0.02)


def test_learned_loss_trains_its_weights_and_checkpoints_them(data, tmp_path):
    settings = TrainSettings(
        iterations=4, batch_size=4, optimizer="adam", lr=1e-2, loss="learned", checkpoint_every=2
    )
    checkpoint = tmp_path / "learned.pt"
    train_backbone(tiny_model(), data, settings, checkpoint, key="L", quiet=True)
    state = load_checkpoint(checkpoint)["weighting"]
    assert state["s_position"].item() != 0.0
    assert state["s_orientation"].item() != -3.0


@pytest.fixture
def data(tiny_scene):
    frames = load_sevenscenes(tiny_scene, None, "train")
    return TrainingImages(read_images(frames, quiet=True), [f.pose for f in frames], 32)


def tiny_model():
    torch.manual_seed(0)
    return PoseNet(input_size=32, width=0.125, feature_dim=32)


SETTINGS = TrainSettings(
    iterations=6, batch_size=4, optimizer="adam", lr=1e-3, beta=5.0, checkpoint_every=2
)


def test_training_lowers_the_loss_on_a_fixed_batch(data):
    settings = TrainSettings(
        iterations=30, batch_size=16, optimizer="adam", lr=3e-3, beta=5.0, random_crops=False
    )
    losses = train_backbone(tiny_model(), data, settings, quiet=True).losses
    assert np.mean(losses[-5:]) < 0.7 * np.mean(losses[:5])


def test_batches_are_random_crops_with_their_labels(data):
    generator = torch.Generator().manual_seed(0)
    images, positions, quaternions = data.batch(torch.tensor([0, 5]), generator, True)
    assert images.shape == (2, 3, 32, 32) and images.dtype == torch.uint8
    assert torch.equal(positions[1], data.positions[5])
    assert torch.equal(quaternions[0], data.quaternions[0])
    assert torch.allclose(quaternions.norm(dim=1), torch.ones(2))


def window_offsets(strip: torch.Tensor, size: int) -> dict[bytes, list[tuple[int, int]]]:
    """Every size x size window of a [3, H, W] strip, by its bytes -> its (y, x) corners."""
    windows: dict[bytes, list[tuple[int, int]]] = {}
    for y in range(strip.shape[1] - size + 1):
        for x in range(strip.shape[2] - size + 1):
            key = strip[:, y : y + size, x : x + size].numpy().tobytes()
            windows.setdefault(key, []).append((y, x))
    return windows


def crop_offsets(data: TrainingImages, draws: int, random_crops: bool = True):
    """Where `draws` crops of image 0 were cut: one (y, x) per crop, and the strip's shape."""
    generator = torch.Generator().manual_seed(0)
    images, _, _ = data.batch(torch.zeros(draws, dtype=torch.long), generator, random_crops)
    windows = window_offsets(data.strips[0].pixels, data.input_size)
    offsets = []
    for crop in images:
        corners = windows.get(crop.numpy().tobytes(), [])
        # This textured scene has no two equal windows, so a crop names its corner.
        assert len(corners) == 1, "a crop that is not exactly one window of the strip"
        offsets.append(corners[0])
    return offsets, tuple(data.strips[0].pixels.shape[1:])


@pytest.fixture(scope="module")
def scene(tiny_scene):
    frames = load_sevenscenes(tiny_scene, None, "train")
    return read_images(frames, quiet=True), [f.pose for f in frames]


def test_crops_at_scale_one_are_every_window_along_the_long_axis_only(scene):
    data = TrainingImages(*scene, input_size=32, crop_scale=1.0)
    offsets, (height, width) = crop_offsets(data, 200)
    assert (height, width) == (32, 43)  # 48x36 scaled to a 32-pixel short side
    assert {y for y, _ in offsets} == {0}
    assert {x for _, x in offsets} == set(range(width - 32 + 1))  # both ends included
    assert len({x for _, x in offsets[:10]}) > 1  # draws differ from one crop to the next


def test_crops_at_posenet_scale_move_along_both_axes(scene):
    data = TrainingImages(*scene, input_size=32, crop_scale=256 / 224)
    offsets, (height, width) = crop_offsets(data, 400)
    assert (height, width) == (37, 49)  # short side round(32 x 256 / 224) = 37
    assert {y for y, _ in offsets} == set(range(height - 32 + 1))
    assert {x for _, x in offsets} == set(range(width - 32 + 1))


def test_without_random_crops_every_draw_is_the_centre_window(scene):
    data = TrainingImages(*scene, input_size=32, crop_scale=256 / 224)
    offsets, (height, width) = crop_offsets(data, 5, random_crops=False)
    assert set(offsets) == {((height - 32) // 2, (width - 32) // 2)}


def test_cosine_schedule_falls_from_lr_to_one_percent_and_is_halfway_at_mid_training():
    settings = TrainSettings(iterations=1000, lr=0.2, lr_schedule="cosine")
    rates = np.array([training.learning_rate(settings, step) for step in range(1001)])
    assert rates[0] == pytest.approx(0.2, rel=1e-12)
    assert rates[-1] == pytest.approx(0.01 * 0.2, rel=1e-12)
    assert rates[500] == pytest.approx(0.505 * 0.2, rel=1e-12)
    # A cosine, not a line (which is also 0.505 halfway): slow at first, fast mid-way.
    quarter = 0.01 + 0.99 * (2 + np.sqrt(2)) / 4
    assert rates[250] == pytest.approx(quarter * 0.2, rel=1e-12)
    assert rates[750] == pytest.approx((1.01 - quarter) * 0.2, rel=1e-12)
    assert np.all(np.diff(rates) < 0)
    constant = TrainSettings(iterations=1000, lr=0.2)
    assert {training.learning_rate(constant, step) for step in (0, 500, 999)} == {0.2}


def test_training_sets_the_scheduled_rate_at_every_step(data, monkeypatch):
    settings = TrainSettings(
        iterations=5, batch_size=2, optimizer="sgd", lr=0.01, lr_schedule="cosine"
    )
    rates = []
    make_optimizer = training.make_optimizer

    def recording(modules, settings):
        optimizer = make_optimizer(modules, settings)
        step = optimizer.step

        def recorded_step(*args, **kwargs):
            rates.append(optimizer.param_groups[0]["lr"])
            return step(*args, **kwargs)

        optimizer.step = recorded_step
        return optimizer

    monkeypatch.setattr(training, "make_optimizer", recording)
    train_backbone(tiny_model(), data, settings, quiet=True)
    cosine = [0.01 + 0.99 * (1 + np.cos(np.pi * step / 5)) / 2 for step in range(5)]
    assert rates == pytest.approx([0.01 * c for c in cosine], rel=1e-12)


class NaNPoseNet(PoseNet):
    """A backbone whose positions are NaN: the loss is NaN at the first step."""

    def forward(self, images):
        output = super().forward(images)
        return PoseOutput(output.positions * float("nan"), output.quaternions, output.features)


@pytest.mark.parametrize(
    "model, settings",
    [
        (lambda: NaNPoseNet(input_size=32, width=0.125, feature_dim=32), SETTINGS),
        (tiny_model, TrainSettings(iterations=50, batch_size=4, optimizer="sgd", lr=1e12)),
    ],
    ids=["nan output", "huge learning rate"],
)
def test_a_non_finite_loss_stops_training_with_a_clear_error(data, tmp_path, model, settings):
    checkpoint = tmp_path / "model.pt"
    with pytest.raises(DataError, match=r"training diverged at step \d+ \(loss (nan|inf)"):
        train_backbone(model(), data, settings, checkpoint, key="k", quiet=True)
    assert not checkpoint.exists() or not load_checkpoint(checkpoint)["complete"]


def test_complete_checkpoint_is_reused(data, tmp_path):
    checkpoint = tmp_path / "model.pt"
    first = tiny_model()
    first_run = train_backbone(first, data, SETTINGS, checkpoint, key="k1", quiet=True)
    assert load_checkpoint(checkpoint)["complete"]
    second = tiny_model()
    calls = []
    original = training.posenet_loss
    training.posenet_loss = lambda *a, **k: calls.append(1) or original(*a, **k)
    try:
        again = train_backbone(second, data, SETTINGS, checkpoint, key="k1", quiet=True)
    finally:
        training.posenet_loss = original
    assert calls == [] and again.reused and not first_run.reused
    assert again.losses == first_run.losses
    for a, b in zip(first.state_dict().values(), second.state_dict().values(), strict=True):
        assert torch.equal(a, b)


def test_interrupted_training_resumes_to_the_same_model(data, tmp_path, monkeypatch):
    uninterrupted = tiny_model()
    expected = train_backbone(uninterrupted, data, SETTINGS, quiet=True).losses

    checkpoint = tmp_path / "model.pt"
    calls = []
    original = training.posenet_loss

    def killed_at_step_5(*args, **kwargs):
        calls.append(1)
        if len(calls) == 5:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(training, "posenet_loss", killed_at_step_5)
    with pytest.raises(KeyboardInterrupt):
        train_backbone(tiny_model(), data, SETTINGS, checkpoint, key="k", quiet=True)
    state = load_checkpoint(checkpoint)
    assert not state["complete"] and state["iteration"] == 4
    monkeypatch.setattr(training, "posenet_loss", original)
    resumed = tiny_model()
    run = train_backbone(resumed, data, SETTINGS, checkpoint, key="k", quiet=True)
    assert not run.reused
    losses = run.losses
    assert np.allclose(losses, expected, rtol=1e-4)
    for a, b in zip(
        uninterrupted.state_dict().values(), resumed.state_dict().values(), strict=True
    ):
        assert torch.allclose(a.float(), b.float(), atol=1e-5)


def test_settings_are_validated():
    with pytest.raises(ConfigError, match="train.iterations"):
        TrainSettings(iterations=0).validate()
    with pytest.raises(ConfigError, match="train.optimizer"):
        TrainSettings(optimizer="rmsprop").validate()
    with pytest.raises(ConfigError, match="train.lr"):
        TrainSettings(lr="fast").validate()


def test_checkpoint_of_another_architecture_is_refused_clearly(data, tmp_path):
    checkpoint = tmp_path / "model.pt"
    train_backbone(tiny_model(), data, SETTINGS, checkpoint, key="k", quiet=True)
    other = PoseNet(input_size=32, width=0.125, feature_dim=16)
    with pytest.raises(DataError, match="does not fit this backbone"):
        train_backbone(other, data, SETTINGS, checkpoint, key="k", quiet=True)
    with pytest.raises(DataError, match="belongs to other settings"):
        train_backbone(tiny_model(), data, SETTINGS, checkpoint, key="other", quiet=True)


def test_a_killed_writers_temporary_is_cleaned_up(data, tmp_path):
    checkpoint = tmp_path / "model.pt"
    stale = tmp_path / ".model.pt.k1ll3d"
    stale.write_bytes(b"half a checkpoint")
    # Unlocked and a day old: no live writer can hold it (a fresh one may be another
    # run's, tests/core/test_atomic_files_concurrency.py).
    day_ago = time.time() - 24 * 3600 - 1
    os.utime(stale, (day_ago, day_ago))
    train_backbone(tiny_model(), data, SETTINGS, checkpoint, key="k", quiet=True)
    assert not stale.exists() and load_checkpoint(checkpoint)["complete"]


def test_training_records_its_crop_scale_in_the_backbone(scene):
    # The pipeline reads it from the backbone, so a saved model always shows the
    # network the field of view it was trained on.
    torch.manual_seed(0)
    backbone = PoseNet(input_size=32, width=0.0625, feature_dim=16)
    data = TrainingImages(*scene, input_size=32, crop_scale=256 / 224)
    train_backbone(backbone, data, TrainSettings(iterations=1, batch_size=2, crop_scale=256 / 224))
    assert float(backbone.crop_scale) == pytest.approx(256 / 224)
    assert "crop_scale" in backbone.state_dict()
    assert Relocalizer(backbone, ExhaustiveIndex(), CentreCrop()).crop_scale == pytest.approx(
        256 / 224
    )


def test_training_refuses_images_cut_with_another_crop_scale(scene):
    data = TrainingImages(*scene, input_size=32, crop_scale=1.0)
    with pytest.raises(ConfigError, match="cut with crop_scale=1 but train.crop_scale=1.14286"):
        train_backbone(PoseNet(input_size=32, width=0.0625, feature_dim=16), data, TrainSettings())


def scaled_copy(data: TrainingImages, factor: float) -> TrainingImages:
    """The same images with every position multiplied by `factor` (another unit)."""
    positions = data.positions.numpy().astype(np.float64) * factor
    poses = [
        Pose(position, quaternion)
        for position, quaternion in zip(positions, data.quaternions.numpy(), strict=True)
    ]
    return TrainingImages(data.images, poses, data.input_size, data.crop_scale)


@pytest.mark.parametrize("loss", ["fixed", "learned"])
def test_normalised_position_frame_trains_the_same_model_at_any_scene_scale(data, loss):
    # A COLMAP model of the same scene in units of 0.25 m is the same training problem:
    # the same step losses, and positions that differ only by the scale. A power of two
    # keeps float rounding out of it (with 0.169 the runs agree to 1e-7 at first, then
    # a tiny random network amplifies the rounding within a few steps).
    settings = TrainSettings(
        iterations=5, batch_size=4, lr=1e-2, beta=5.0, loss=loss, position_frame="normalised"
    )
    metric, scaled = tiny_model(), tiny_model()
    metric_run = train_backbone(metric, data, settings, quiet=True)
    scaled_run = train_backbone(scaled, scaled_copy(data, 4.0), settings, quiet=True)
    np.testing.assert_allclose(scaled_run.losses, metric_run.losses, rtol=1e-6)
    images = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(1))
    with torch.inference_mode():
        metric_positions = metric(images).positions
        scaled_positions = scaled(images).positions
    np.testing.assert_allclose(scaled_positions / 4.0, metric_positions, rtol=1e-5, atol=1e-6)


def test_world_position_frame_keeps_posenets_beta_per_pose_unit(data):
    # The paper's beta is per metre: in the world frame a scaled scene is another problem.
    settings = TrainSettings(iterations=2, batch_size=4, optimizer="adam", lr=1e-3, beta=5.0)
    assert settings.position_frame == "world"
    metric_run = train_backbone(tiny_model(), data, settings, quiet=True)
    scaled_run = train_backbone(tiny_model(), scaled_copy(data, 10.0), settings, quiet=True)
    assert scaled_run.losses[0] > 2 * metric_run.losses[0]


def test_normalised_loss_divides_position_errors_by_the_position_scale():
    positions, true_q = torch.tensor([[3.0, 4.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    position, orientation = head_errors(positions, true_q, torch.zeros(1, 3), true_q, 2.5)
    assert position.item() == pytest.approx(2.0)
    assert orientation.item() == pytest.approx(0.0)


def test_an_unknown_position_frame_is_refused_by_name():
    with pytest.raises(ConfigError, match="train.position_frame"):
        TrainSettings(position_frame="metres").validate()
