"""What loading a model file trusts: registered plugins only, never a class the file names.

Each crafted file is a real saved model with one part's class or options edited, as an
attacker (or a damaged copy) would leave it.
"""

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from relocfw import Pose, Relocalizer, load_model, save_model
from relocfw.core.errors import ConfigError, DataError
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.retrieval_refiner import RetrievalRefiner
from tests.cli_runs import relocfw

OPTIONS = {"backbone": {"input_size": 32, "width": 0.125, "feature_dim": 16}}


class UnregisteredIndex(ExhaustiveIndex):
    """A working SimilarityIndex that no config group registers."""


def tiny_relocalizer(crop=None, index=None, refiner=None) -> Relocalizer:
    torch.manual_seed(0)
    backbone = PoseNet(**OPTIONS["backbone"]).eval()
    relocalizer = Relocalizer(
        backbone, index or ExhaustiveIndex(), crop or CentreCrop(), refiner=refiner
    )
    poses = [Pose([0.0, 0, 0], [1, 0, 0, 0]), Pose([1.0, 0, 0], [0, 1, 0, 0])]
    relocalizer.fit([np.zeros((36, 48, 3), np.uint8), np.full((36, 48, 3), 200, np.uint8)], poses)
    return relocalizer


@pytest.fixture(scope="module")
def saved_payload(tmp_path_factory):
    """The payload of a genuine model file, to edit into crafted ones."""
    path = save_model(
        tmp_path_factory.mktemp("genuine") / "model.relocfw", tiny_relocalizer(), OPTIONS, {}
    )
    assert isinstance(load_model(path), Relocalizer)  # the unedited file loads
    return torch.load(path, weights_only=True)


@pytest.fixture(scope="module")
def retrieval_payload(tmp_path_factory):
    """The payload of a genuine model file with a stored refiner (refine=retrieval)."""
    path = save_model(
        tmp_path_factory.mktemp("genuine") / "model.relocfw",
        tiny_relocalizer(refiner=RetrievalRefiner(k=2)),
        {**OPTIONS, "refine": {"k": 2}},
        {},
    )
    assert isinstance(load_model(path).refiner, RetrievalRefiner)
    return torch.load(path, weights_only=True)


def crafted(payload: dict, tmp_path: Path, part: str, **fields) -> Path:
    """A copy of `payload` with fields of `part` replaced, written as a model file."""
    edited = {**payload, part: {**payload[part], **fields}}
    path = tmp_path / "crafted.relocfw"
    torch.save(edited, path)
    return path


@pytest.mark.parametrize("part", ["index", "crop", "refine"])
def test_a_model_file_naming_os_system_runs_nothing(retrieval_payload, tmp_path, part):
    marker = tmp_path / "MARKER"
    # os.system's parameter is `command`: the options are exactly its call.
    path = crafted(
        retrieval_payload,
        tmp_path,
        part,
        **{"class": "os.system", "options": {"command": f"touch {marker}"}},
    )
    with pytest.raises(Exception) as caught:  # noqa: B017 - the type is checked below
        load_model(path)
    assert not marker.exists(), "loading the model file ran a shell command"
    assert isinstance(caught.value, DataError), caught.value
    message = str(caught.value)
    assert str(path) in message and "'os.system'" in message and "\n" not in message


def test_an_unregistered_module_is_not_even_imported(saved_payload, tmp_path, monkeypatch):
    # Importing a module runs it: the class path is refused before any import.
    marker = tmp_path / "IMPORTED"
    (tmp_path / "bait_module.py").write_text(
        f"open({str(marker)!r}, 'w').close()\nclass Index: pass\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    path = crafted(saved_payload, tmp_path, "index", **{"class": "bait_module.Index"})
    with pytest.raises(DataError, match="'bait_module.Index': it is not a registered"):
        load_model(path)
    assert not marker.exists() and "bait_module" not in sys.modules


@pytest.mark.parametrize(
    "class_path",
    [
        "collections.OrderedDict",  # exists, callable with the options, not a plugin
        f"{__name__}.UnregisteredIndex",  # a working SimilarityIndex with no YAML
        "relocfw.plugins.centre_crop.CentreCrop",  # registered, but in the crop group
    ],
    ids=["not a plugin", "unregistered index", "another group's plugin"],
)
def test_a_class_that_is_not_a_registered_index_is_refused(saved_payload, tmp_path, class_path):
    path = crafted(saved_payload, tmp_path, "index", **{"class": class_path})
    with pytest.raises(DataError) as caught:
        load_model(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: refused the index class {class_path!r}")
    assert "registered SimilarityIndex plugin" in message


def test_a_refiner_class_must_be_a_registered_pose_refiner(retrieval_payload, tmp_path):
    # Registered, but in the index group: not a refiner.
    class_path = "relocfw.plugins.exhaustive_index.ExhaustiveIndex"
    path = crafted(retrieval_payload, tmp_path, "refine", **{"class": class_path})
    with pytest.raises(DataError) as caught:
        load_model(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: refused the refine class {class_path!r}")
    assert "registered PoseRefiner plugin" in message


def test_a_refiner_option_out_of_range_is_one_data_error(retrieval_payload, tmp_path):
    path = crafted(retrieval_payload, tmp_path, "refine", options={"k": 0})
    with pytest.raises(DataError) as caught:
        load_model(path)
    assert str(caught.value) == (
        f"{path}: damaged model file (refine: refine.k must be at least 1, got 0)"
    )


def test_a_registered_target_that_is_not_the_interface_is_refused(
    saved_payload, tmp_path, monkeypatch
):
    # A plugin package whose index YAML names a class that is no SimilarityIndex.
    site = tmp_path / "site"
    info = site / "plainplug-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: plainplug\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[relocfw.configs]\nmain = plainplug.conf\n")
    for name, body in {
        "__init__.py": "",
        "plain.py": "class NotAnIndex:\n    pass\n",
        "conf/__init__.py": "",
        "conf/index/plain.yaml": "# Not an index.\n_target_: plainplug.plain.NotAnIndex\n",
    }.items():
        (site / "plainplug" / name).parent.mkdir(parents=True, exist_ok=True)
        (site / "plainplug" / name).write_text(body)
    monkeypatch.syspath_prepend(str(site))
    path = crafted(saved_payload, tmp_path, "index", **{"class": "plainplug.plain.NotAnIndex"})
    with pytest.raises(DataError, match=r"'plainplug.plain.NotAnIndex': it is not a Similarity"):
        load_model(path)


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"class": 5}, "index class is 5, not a name"),
        ({"class": None}, "index class is None, not a name"),
        ({"options": ["command"]}, "index options are list, not a mapping of option names"),
        ({"options": "touch x"}, "index options are str, not a mapping of option names"),
    ],
    ids=["integer class", "no class", "list options", "text options"],
)
def test_malformed_parts_are_one_data_error(saved_payload, tmp_path, fields, message):
    path = crafted(saved_payload, tmp_path, "index", **fields)
    with pytest.raises(DataError) as caught:
        load_model(path)
    assert str(caught.value) == f"{path}: damaged model file ({message})"


def test_a_part_that_is_not_a_mapping_is_one_data_error(saved_payload, tmp_path):
    path = tmp_path / "crafted.relocfw"
    torch.save({**saved_payload, "crop": "os.system"}, path)
    with pytest.raises(DataError, match=r"damaged model file \(crop is not a mapping\)"):
        load_model(path)


def test_a_registered_third_party_plugin_still_loads(tmp_path):
    search = pytest.importorskip(
        "relocfw_coarse_to_fine.search", reason="pip install -e examples/relocfw-coarse-to-fine"
    )
    relocalizer = tiny_relocalizer(crop=search.CoarseToFineCrop(points=3, shrink=2.0))
    options = {**OPTIONS, "crop": {"points": 3, "shrink": 2.0}}
    path = save_model(tmp_path / "model.relocfw", relocalizer, options, {})
    loaded = load_model(path)
    assert type(loaded.search) is search.CoarseToFineCrop
    assert (loaded.search.points, loaded.search.shrink) == (3, 2.0)
    image = np.full((36, 48, 3), 90, np.uint8)
    assert loaded.localize(image).crop == relocalizer.localize(image).crop


def test_saving_an_unregistered_class_is_refused_before_writing(tmp_path):
    # The file would be refused on loading: better to say so when it is written.
    path = tmp_path / "model.relocfw"
    with pytest.raises(ConfigError, match=rf"cannot save the index {__name__}.UnregisteredIndex"):
        save_model(path, tiny_relocalizer(index=UnregisteredIndex()), OPTIONS, {})
    assert not path.exists()


def test_the_cli_refuses_a_crafted_model_file_in_one_line(saved_payload, tmp_path):
    marker = tmp_path / "MARKER"
    path = crafted(
        saved_payload,
        tmp_path,
        "index",
        **{"class": "os.system", "options": {"command": f"touch {marker}"}},
    )
    assert cv2.imwrite(str(tmp_path / "query.png"), np.zeros((36, 48, 3), np.uint8))
    result = relocfw(
        ["task=localize", f"localize.model={path}", "localize.images=query.png"], tmp_path
    )
    assert result.returncode == 2, result.stdout
    assert not marker.exists()
    (line,) = result.stderr.strip().splitlines()
    assert str(path) in line and "'os.system'" in line
