"""ONNX export (task=export, the robots' network) and the onnxruntime engine as the
CLI and scene images meet it (engine=onnx; tests/model/test_onnx_engine.py has the
engine's own tests)."""

import csv
import importlib
import re
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from relocfw.app.tasks import export, localize
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import Strip, to_network_input
from relocfw.core.pipeline import Relocalizer
from relocfw.core.query_options import QueryOptions
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.model import onnx_export
from relocfw.model.model_file import load_model, save_model
from relocfw.model.ncnn_engine import ncnn_installed
from relocfw.model.onnx_backbone import OnnxBackbone
from relocfw.model.onnx_engine import (
    EngineOptions,
    EngineUnavailableError,
    file_digest,
    onnx_engine,
)
from relocfw.model.onnx_export import export_onnx, onnx_path
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from tests.cli_runs import relocfw, relocfw_here
from tests.conftest import TINY_OVERRIDES

# relocfw imports neither package until it needs one, so the skips can follow the imports.
pytest.importorskip("onnx", reason='onnx not installed (pip install "relocfw[onnx]")')
ort = pytest.importorskip("onnxruntime", reason='onnxruntime not installed ("relocfw[onnx]")')

TOLERANCE = 1e-4


def tiny_posenet(seed=0, **options):
    torch.manual_seed(seed)
    backbone = PoseNet(input_size=32, width=0.125, feature_dim=32, **options).eval()
    # A frame away from the origin, so the graph must map positions back itself.
    backbone.set_position_normalisation(np.array([1.0, -2.0, 3.0]), 2.5)
    backbone.set_crop_scale(1.142857)
    return backbone


def tiny_efficientnet():
    pytest.importorskip("efficientnet_lite_pytorch", reason="relocfw[efficientnet] not installed")
    from relocfw.plugins.efficientnet_lite import EfficientNetLite0

    torch.manual_seed(0)
    backbone = EfficientNetLite0(pretrained=False, input_size=32, feature_dim=32).eval()
    backbone.set_position_normalisation(np.array([1.0, -2.0, 3.0]), 2.5)
    return backbone


@pytest.mark.parametrize("make", [tiny_posenet, tiny_efficientnet], ids=["posenet", "efficientnet"])
def test_onnx_network_answers_as_torch(tmp_path, make):
    backbone = make()
    path = tmp_path / "net.onnx"
    differences = export_onnx(backbone, path)
    assert set(differences) == {"positions", "quaternions", "features"}
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (image_input,) = session.get_inputs()
    assert image_input.name == "images" and image_input.shape[1:] == [3, 32, 32]
    assert isinstance(image_input.shape[0], str)  # the batch is dynamic
    assert [o.name for o in session.get_outputs()] == ["positions", "quaternions", "features"]
    metadata = session.get_modelmeta().custom_metadata_map
    assert metadata["relocfw.input_size"] == "32"
    assert float(metadata["relocfw.crop_scale"]) == pytest.approx(float(backbone.crop_scale))
    # Five images: neither the traced batch (2) nor the check batch (3).
    images = torch.rand(5, 3, 32, 32, generator=torch.Generator().manual_seed(1))
    positions, quaternions, features = session.run(None, {"images": images.numpy()})
    with torch.no_grad():
        expected = backbone(images)
    assert np.allclose(positions, expected.positions.numpy(), atol=TOLERANCE)
    assert np.allclose(quaternions, expected.quaternions.numpy(), atol=TOLERANCE)
    assert np.allclose(features, expected.features.numpy(), atol=TOLERANCE)
    assert features.shape == (5, 32)
    assert np.allclose(np.linalg.norm(quaternions, axis=1), 1.0, atol=1e-5)


def test_export_is_the_dropout_free_network_and_leaves_the_backbone_as_it_was(tmp_path):
    backbone = tiny_posenet(mc_samples=5, dropout_variant="kendall")
    export_onnx(backbone, tmp_path / "net.onnx")
    assert backbone.mc_samples == 5 and not backbone.training
    session = ort.InferenceSession(str(tmp_path / "net.onnx"), providers=["CPUExecutionProvider"])
    images = torch.rand(3, 3, 32, 32)
    positions, _, features = session.run(None, {"images": images.numpy()})
    backbone.mc_samples = 0
    with torch.no_grad():
        expected = backbone(images)
    assert np.allclose(positions, expected.positions.numpy(), atol=TOLERANCE)
    assert np.allclose(features, expected.features.numpy(), atol=TOLERANCE)


def test_a_failed_check_writes_nothing(tmp_path, monkeypatch):
    path = tmp_path / "net.onnx"
    path.write_bytes(b"the previous export")
    monkeypatch.setattr(onnx_export, "TOLERANCE", -1.0)  # no answer can pass
    with pytest.raises(DataError, match="not written"):
        export_onnx(tiny_posenet(), path)
    assert path.read_bytes() == b"the previous export"
    assert [p.name for p in tmp_path.iterdir()] == ["net.onnx"]  # no temporary left


def test_missing_packages_name_the_extra(tmp_path, monkeypatch):
    real = importlib.import_module

    def without_onnx(name, *args):
        if name.startswith("onnx"):
            raise ImportError(name)
        return real(name, *args)

    monkeypatch.setattr(onnx_export.importlib, "import_module", without_onnx)
    with pytest.raises(ConfigError, match=r'pip install "relocfw\[onnx\]"'):
        export_onnx(tiny_posenet(), tmp_path / "net.onnx")
    # The engine says which package it lacks (the CLI then runs torch, in one line).
    monkeypatch.setitem(sys.modules, "onnxruntime", None)
    message = r"""engine=onnx needs 'onnxruntime' \(pip install "relocfw\[onnx\]"\)"""
    with pytest.raises(EngineUnavailableError, match=message):
        onnx_engine(tiny_posenet(), tmp_path / "net.pt")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


ONE_THREAD = EngineOptions(threads=1)


def test_the_engine_rebuilds_a_graph_of_other_weights_and_exports_a_missing_one(tmp_path):
    owner = tmp_path / "net.pt"
    notes = []
    onnx_engine(tiny_posenet(seed=0), owner, ONE_THREAD, say=notes.append)  # nothing cached
    assert notes == []
    full, maps = tmp_path / "net.pt-full.onnx", tmp_path / "net.pt-maps.onnx"
    assert sorted(tmp_path.iterdir()) == [full, maps]
    before = full.read_bytes()
    engine = onnx_engine(tiny_posenet(seed=1), owner, ONE_THREAD, say=notes.append)
    assert notes == [
        f"note: rebuilt {full}: it was exported from other weights",
        f"note: rebuilt {maps}: it was exported from other weights",
    ]
    assert full.read_bytes() != before
    images = torch.rand(3, 3, 32, 32, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        want = tiny_posenet(seed=1)(images)
        got = engine(images)
    assert np.allclose(got.positions.numpy(), want.positions.numpy(), atol=TOLERANCE)
    assert np.allclose(got.features.numpy(), want.features.numpy(), atol=TOLERANCE)


@pytest.fixture
def scene_images(tiny_scene):
    train = load_sevenscenes(tiny_scene, None, "train")
    test = load_sevenscenes(tiny_scene, None, "test")
    return read_images(train, quiet=True), read_images(test, quiet=True)


def test_onnx_backbone_gives_the_torch_crops_and_poses(tmp_path, scene_images):
    train, test = scene_images
    backbone = tiny_posenet()
    relocalizer = Relocalizer(
        backbone, KMeansIndex(k=4), GeneticCropSearch(seed=0), QueryOptions(batch_size=5)
    )
    features = relocalizer.fit(train)
    swapped = relocalizer.replace(backbone=onnx_engine(backbone, tmp_path / "net.pt", ONE_THREAD))
    assert isinstance(swapped.backbone, OnnxBackbone) and swapped.index is relocalizer.index
    assert swapped.crop_scale == pytest.approx(relocalizer.crop_scale)
    assert np.allclose(swapped.describe(train), features, atol=TOLERANCE)  # the map's view
    for image in test:
        want, got = relocalizer.localize(image), swapped.localize(image)
        assert got.crop == want.crop and got.evaluations == want.evaluations
        assert np.allclose(got.pose.position, want.pose.position, atol=TOLERANCE)
        assert np.allclose(got.pose.quaternion, want.pose.quaternion, atol=TOLERANCE)
    # Queries localized together share forward passes through the session as well.
    together = swapped.localize_many(test, queries_at_once=2)
    assert [a.crop for a in together] == [relocalizer.localize(i).crop for i in test]


def test_the_engine_runs_what_the_robots_graph_could_not(tmp_path, scene_images):
    """Shared scoring and Monte Carlo dropout, refused by the old localize.backend=onnx,
    run on the engine's maps graph and give torch's answers."""
    train, test = scene_images
    backbone = tiny_posenet(mc_samples=4, dropout_variant="kendall")
    engine = onnx_engine(backbone, tmp_path / "net.pt", ONE_THREAD)
    assert sorted(engine.sessions) == ["full", "maps"]
    shared = Relocalizer(
        backbone, ExhaustiveIndex(), GeneticCropSearch(seed=0), QueryOptions(scoring="shared")
    )
    shared.fit(train)
    swapped = shared.replace(backbone=engine)
    for image in test:
        want, got = shared.localize(image), swapped.localize(image)
        assert got.crop == want.crop
        assert np.allclose(got.pose.position, want.pose.position, atol=TOLERANCE)
        assert got.position_spread == pytest.approx(want.position_spread, abs=TOLERANCE)


def test_export_task_says_monte_carlo_sampling_is_left_out(tmp_path, capsys):
    backbone = tiny_posenet(mc_samples=3)
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), CentreCrop())
    relocalizer.fit([np.zeros((36, 48, 3), np.uint8), np.full((36, 48, 3), 200, np.uint8)])
    options = {
        "backbone": {"input_size": 32, "width": 0.125, "feature_dim": 32, "mc_samples": 3},
        "index": {},
        "crop": {},
    }
    model = save_model(tmp_path / "model.relocfw", relocalizer, options, {})
    cfg = OmegaConf.create({"export": {"model": str(model), "out": None}})
    export.run(cfg, torch.device("cpu"), None)
    printed = capsys.readouterr().out
    assert "mc_samples=3" in printed and "dropout-free" in printed
    assert onnx_path(model) == tmp_path / "model.relocfw.onnx" and onnx_path(model).is_file()
    robots = onnx_path(model).read_bytes()
    cfg = OmegaConf.create(
        {
            "localize": {"model": str(model)},
            "query": {"scoring": "plain", "batch_size": 8},
            "export": {"out": None},
            "engine": "onnx",
            "onnx": {"threads": 1, "int8": "none", "spinning": False},
            "quiet": True,
        }
    )
    # ... but the engine samples: its graphs (not the robot's) run the dropout-free part.
    loaded = localize.load_for_localize(cfg, torch.device("cpu"))
    assert isinstance(loaded.backbone, OnnxBackbone) and loaded.backbone.mc_samples == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "model.relocfw",
        "model.relocfw-full.onnx",
        "model.relocfw-maps.onnx",
        "model.relocfw.onnx",
    ]
    assert onnx_path(model).read_bytes() == robots
    assert capsys.readouterr().out == ""  # quiet, and nothing to note


def saved_tiny_model(folder: Path) -> Path:
    relocalizer = Relocalizer(tiny_posenet(), ExhaustiveIndex(), CentreCrop())
    relocalizer.fit([np.zeros((36, 48, 3), np.uint8), np.full((36, 48, 3), 200, np.uint8)])
    options = {"backbone": {"input_size": 32, "width": 0.125, "feature_dim": 32}}
    return save_model(folder / "model.relocfw", relocalizer, options, {})


def export_to(model: Path, out: str | None) -> None:
    cfg = OmegaConf.create({"export": {"model": str(model), "out": out}})
    export.run(cfg, torch.device("cpu"), None)


@pytest.mark.parametrize(
    ("out", "message"),
    [
        ("model.relocfw", "export.out=model.relocfw is the model file itself"),
        ("./model.relocfw", "export.out=./model.relocfw is the model file itself"),
        ("link.onnx", "export.out=link.onnx is the model file itself"),  # a link to it
        ("notes.txt", "export.out=notes.txt: notes.txt exists and is not an ONNX file"),
        ("folder", "export.out=folder is a folder, not a file"),
    ],
    ids=["the model", "the model via ./", "a link to the model", "another file", "a folder"],
)
def test_export_never_replaces_the_model_or_a_file_that_is_not_onnx(
    tmp_path, monkeypatch, out, message
):
    model = saved_tiny_model(tmp_path)
    (tmp_path / "link.onnx").symlink_to(model)
    (tmp_path / "notes.txt").write_text("a user's notes")
    (tmp_path / "folder").mkdir()
    kept = model.read_bytes()
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError) as error:
        export_to(Path("model.relocfw"), out)
    assert str(error.value).startswith(message)
    assert model.read_bytes() == kept and load_model(model).metadata == {}
    assert (tmp_path / "notes.txt").read_text() == "a user's notes"
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "folder",
        "link.onnx",
        "model.relocfw",
        "notes.txt",
    ]


def test_export_replaces_an_earlier_onnx_file(tmp_path):
    model = saved_tiny_model(tmp_path)
    earlier = tmp_path / "robot.onnx"
    earlier.write_bytes(b"an earlier export")
    export_to(model, str(earlier))
    session = ort.InferenceSession(str(earlier), providers=["CPUExecutionProvider"])
    assert [o.name for o in session.get_outputs()] == ["positions", "quaternions", "features"]


@pytest.fixture(scope="module")
def trained_model(tmp_path_factory):
    home = tmp_path_factory.mktemp("onnx-run")
    result = relocfw([*TINY_OVERRIDES, f"hydra.run.dir={home / 'run'}"], home, home / "cache")
    assert result.returncode == 0, result.stderr
    scene = next((home / "cache" / "scenes").iterdir())
    return home, home / "run" / "model.relocfw", scene / "seq-03"


def localization_rows(run_dir):
    with open(run_dir / "localization.csv") as stream:
        return list(csv.DictReader(stream))


def localize_run(trained_model, model, run_dir, *args):
    home, _, images = trained_model
    return relocfw(
        [
            "task=localize",
            f"localize.model={model}",
            f"localize.images={images}/*.color.png",
            f"hydra.run.dir={run_dir}",
            "quiet=true",
            *args,
        ],
        home,
        home / "cache",
    )


def test_cli_export_then_localize_on_either_engine(trained_model):
    home, model, images = trained_model
    # model= in the spelling before issue 21: task=export reads it as export.model.
    exported = relocfw(["task=export", f"model={model}"], home, home / "cache")
    assert exported.returncode == 0, exported.stderr
    assert exported.stderr.splitlines() == [
        f"note: model= is now export.model= (read as export.model={model})"
    ]
    assert f"ONNX network: {model}.onnx" in exported.stdout
    robots = Path(f"{model}.onnx").read_bytes()
    runs = {}
    # engine=ncnn too where relocfw[ncnn] is installed (it is in relocfw[test]).
    engines = ("torch", "onnx", "ncnn") if ncnn_installed() else ("torch", "onnx")
    for engine in engines:
        runs[engine] = home / f"localize-{engine}"
        result = localize_run(trained_model, model, runs[engine], f"engine={engine}")
        assert result.returncode == 0, result.stderr
        assert "note:" not in result.stdout + result.stderr  # the engine ran, no fallback
    torch_poses = np.loadtxt(runs["torch"] / "poses.txt")
    assert torch_poses.shape == (4, 8)
    for engine in engines[1:]:
        poses = np.loadtxt(runs[engine] / "poses.txt")
        assert poses.shape == torch_poses.shape
        assert np.allclose(poses, torch_poses, atol=TOLERANCE), engine
        crops = [
            [(r["crop_x"], r["crop_y"], r["crop_size"]) for r in localization_rows(runs[name])]
            for name in ("torch", engine)
        ]
        assert crops[0] == crops[1], engine
    # The engine's graphs are cached by the model file's content, not beside it; the
    # robot's export is not what it runs, and stays as task=export wrote it.
    cached = {p.name for p in (home / "cache" / "graphs" / file_digest(model)).iterdir()}
    assert {"model.relocfw-full.onnx", "model.relocfw-maps.onnx"} <= cached
    assert not list(model.parent.glob("model.relocfw-*"))
    assert Path(f"{model}.onnx").read_bytes() == robots


def test_cli_localize_backend_is_read_as_engine_and_needs_no_export(trained_model, tmp_path):
    """The old spelling runs the engine, with one note; shared scoring (which the old
    backend refused) runs on it, and no task=export is needed first."""
    home, model, images = trained_model
    lone = tmp_path / "model.relocfw"  # a model file with nothing beside it
    lone.write_bytes(model.read_bytes())
    args = ["localize.backend=onnx", "query.scoring=shared"]
    result = localize_run(trained_model, lone, tmp_path / "run", *args)
    assert result.returncode == 0, result.stderr
    assert result.stderr.splitlines() == [
        "note: localize.backend= is now engine= (read as engine=onnx)"
    ]
    assert np.all(np.isfinite(np.loadtxt(tmp_path / "run" / "poses.txt")))
    assert len(localization_rows(tmp_path / "run")) == 4
    # The model file's folder gets no graph: they are cached by its content.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.relocfw", "run"]
    cached = {p.name for p in (home / "cache" / "graphs" / file_digest(lone)).iterdir()}
    assert {"model.relocfw-full.onnx", "model.relocfw-maps.onnx"} <= cached


def test_cli_localize_with_an_int8_scout(trained_model, tmp_path):
    """query.scoring=scout on a model file: the static int8 graph kept beside it (as
    task=relocalize keeps it) scouts, the float32 graphs answer."""
    from relocfw.core.imaging import read_rgb
    from relocfw.model.model_file import load_model
    from relocfw.model.onnx_engine import EngineOptions, onnx_engine

    home, model, images = trained_model
    lone = tmp_path / "model.relocfw"
    lone.write_bytes(model.read_bytes())
    args = ["onnx.int8=static", "query.scoring=scout", "query.rerank=2"]
    # No map images at hand in task=localize: one message naming what to run.
    missing = localize_run(trained_model, lone, tmp_path / "first", *args)
    assert missing.returncode == 2
    assert "onnx.int8=static calibrates on map images" in missing.stderr
    calibration = [read_rgb(path) for path in sorted(images.glob("*.color.png"))]
    options = EngineOptions(threads=1, int8="static", scout=True)
    onnx_engine(load_model(lone, "cpu").backbone, lone, options, calibration)
    result = localize_run(trained_model, lone, tmp_path / "run", *args)
    assert result.returncode == 0, result.stderr
    assert np.all(np.isfinite(np.loadtxt(tmp_path / "run" / "poses.txt")))
    assert len(localization_rows(tmp_path / "run")) == 4
    assert sorted(p.name for p in tmp_path.glob("model.relocfw-*")) == [
        "model.relocfw-full.int8-static.onnx",
        "model.relocfw-full.onnx",
        "model.relocfw-maps.onnx",
    ]
    # Without onnx.int8 there is no scout: one message, nothing localized.
    refused = localize_run(trained_model, lone, tmp_path / "again", "query.scoring=scout")
    assert refused.returncode == 2
    assert "query.scoring=scout scores candidate crops with the static int8" in refused.stderr


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["engine=tensorrt"],
            "engine=tensorrt: Invalid value 'tensorrt', expected one of [auto, torch, onnx, ncnn]",
        ),
        (
            ["onnx.int8=int4"],
            "onnx.int8=int4: Invalid value 'int4', expected one of "
            "[none, dynamic, static, static_8bit]",
        ),
        (
            ["engine=torch", "onnx.int8=dynamic"],
            "onnx.int8=dynamic quantises the onnxruntime graphs, but the network runs on torch "
            "here (engine=torch)",
        ),
        (["onnx.threads=0"], "onnx.threads must be >= 1 (null: every core), got 0"),
        (
            ["engine=onnx", "onnx.int8=static"],
            "onnx.int8=static calibrates on map images, and none are at hand here",
        ),
    ],
    ids=["unknown engine", "unknown int8", "int8 on torch", "no threads", "static, no map"],
)
def test_cli_bad_engine_inputs(trained_model, tmp_path, args, message):
    home, model, images = trained_model
    lone = tmp_path / "model.relocfw"  # a model file with no graphs beside it
    lone.write_bytes(model.read_bytes())
    result = relocfw_here(
        ["task=localize", f"localize.model={lone}", f"localize.images={images}/*.color.png", *args],
        tmp_path,
        home,
    )
    assert result.returncode == 2, result.stdout
    assert message in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert not list(tmp_path.glob("*int8*"))


def test_cli_export_onto_the_model_file_is_refused_in_one_line(trained_model, tmp_path):
    home, model, _ = trained_model
    lone = tmp_path / "m"
    lone.write_bytes(model.read_bytes())
    result = relocfw_here(["task=export", "export.model=m", "export.out=./m"], tmp_path, home)
    assert result.returncode == 2, result.stdout
    (line,) = result.stderr.strip().splitlines()
    assert "export.out=./m is the model file itself" in line
    assert lone.read_bytes() == model.read_bytes()


def docs_code_blocks():
    text = (Path(__file__).resolve().parents[2] / "docs" / "onnx.md").read_text()
    return re.findall(r"```python\n(.*?)```", text, flags=re.DOTALL)


@pytest.mark.parametrize("crop_scale", [1.0, 1.142857])
def test_the_robot_recipe_in_the_docs_is_what_relocfw_does(tmp_path, monkeypatch, crop_scale):
    """docs/onnx.md's preprocessing cuts relocfw's centre window, and its session answers
    with relocfw's centre-crop pose."""
    recipe, robot = docs_code_blocks()
    namespace = {}
    exec(recipe, namespace)  # our own docs: the code a reader copies
    rng = np.random.default_rng(0)
    for height, width in ((36, 48), (48, 36), (40, 40), (480, 640), (37, 101)):
        image = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
        strip = Strip(image, 32, crop_scale)
        want = to_network_input(strip.cut(strip.window(strip.centre_crop()))[None]).numpy()
        got = namespace["preprocess"](image, 32, crop_scale)
        assert got.dtype == np.float32 and np.array_equal(got, want), (height, width)
    backbone = tiny_posenet()
    backbone.set_crop_scale(crop_scale)
    export_onnx(backbone, tmp_path / "model.relocfw.onnx")
    cv2.imwrite(str(tmp_path / "frame.png"), image[:, :, ::-1])
    monkeypatch.chdir(tmp_path)
    exec(robot, namespace)
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), CentreCrop())
    relocalizer.fit([image])
    pose = relocalizer.localize(image).pose
    assert np.allclose(namespace["positions"][0], pose.position, atol=TOLERANCE)
    quaternion = namespace["quaternions"][0] * np.sign(namespace["quaternions"][0][0])
    assert np.allclose(quaternion, pose.quaternion, atol=TOLERANCE)
