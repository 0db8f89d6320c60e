"""engine=ncnn (relocfw.model.ncnn_engine): every query path answers as torch does,
cached ncnn files that cannot serve are converted again, and a missing package or a
failed conversion says why in one line.

Each tiny network is converted once for the module (`converted`); tests that damage
a cache work on copies of its files. The query paths and the comparison with torch
are engine=onnx's (tests/model/test_onnx_engine.py).
"""

import ast
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from relocfw.app.engines import on_engine, wanted_engine
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.pipeline import Relocalizer
from relocfw.core.query_options import QueryOptions
from relocfw.model import ncnn_engine as ncnn_module
from relocfw.model.ncnn_engine import NcnnSession, ncnn_engine, ncnn_files
from relocfw.model.onnx_engine import EngineOptions, EngineUnavailableError, graph_path
from relocfw.model.onnx_graphs import KINDS, kinds_needed
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.kmeans_index import KMeansIndex

if not ncnn_module.ncnn_installed():
    pytest.skip('ncnn or pnnx not installed (pip install "relocfw[ncnn]")', allow_module_level=True)
from tests.model.test_onnx_engine import (  # noqa: E402 - onnx's skips come with it
    PATHS,
    QUERY_PATHS,
    TOLERANCE,
    Built,
    Images,
    assert_same_answer,
    count_runs,
    engine_config,
    engines_made_once,
    seeded_images,
    tiny_posenet,
)
from tests.model.test_onnx_engine import cached_copy as onnx_cached_copy  # noqa: E402

ONE_THREAD = EngineOptions(threads=1)


@pytest.fixture(scope="module")
def images() -> Images:
    return seeded_images()


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    """converted(variant, seed): the network on ncnn, converted once a module."""
    return engines_made_once(tmp_path_factory, ncnn_engine, "ncnn")


def cached_copy(net: Built, folder: Path) -> Path:
    """A new owner in `folder` with copies of `net`'s ONNX graphs and ncnn files."""
    owner = onnx_cached_copy(net, folder)
    for kind in kinds_needed(net.backbone):
        for part, path in ncnn_files(net.owner, kind).items():
            shutil.copyfile(path, ncnn_files(owner, kind)[part])
    return owner


def no_conversion(*args, **kwargs):
    pytest.fail("pnnx ran, but the cached files should have served")


@pytest.mark.parametrize(("variant", "case"), QUERY_PATHS)
def test_each_query_path_answers_as_torch(converted, images, monkeypatch, variant, case):
    make_search, options, mc_samples = PATHS[case]
    net = converted(variant)
    assert all(isinstance(s, NcnnSession) for s in net.engine.sessions.values())
    monkeypatch.setattr(net.backbone, "mc_samples", mc_samples)
    torch_way = Relocalizer(net.backbone, KMeansIndex(k=3), make_search(), QueryOptions(**options))
    features = torch_way.fit(images.map)
    runs = count_runs(net.engine, monkeypatch)
    engine_way = torch_way.replace(backbone=net.engine)
    np.testing.assert_allclose(engine_way.describe(images.map), features, rtol=0, atol=TOLERANCE)
    for image in images.queries:
        assert_same_answer(engine_way.localize(image), torch_way.localize(image))
    used = {kind for kind, session in runs.items() if session.runs}
    assert "full" in used
    if options.get("scoring") == "shared" or (mc_samples and variant != "all"):
        assert "maps" in used
    if mc_samples and variant == "all":
        assert "lower" in used


@pytest.mark.parametrize(
    ("variant", "kinds"), [("head", ["full", "maps"]), ("all", ["full", "maps", "lower"])]
)
def test_the_files_are_cached_beside_the_owner_and_reused(
    converted, tmp_path, monkeypatch, variant, kinds
):
    net = converted(variant)
    assert sorted(net.engine.sessions) == sorted(kinds)
    for kind in kinds:
        files = ncnn_files(net.owner, KINDS[kind])
        record = json.loads(files["json"].read_text())
        onnx_bytes = graph_path(net.owner, KINDS[kind]).read_bytes()
        assert record["onnx_sha256"] == ncnn_module.hashlib.sha256(onnx_bytes).hexdigest()
        assert set(record["versions"]) == {"ncnn", "pnnx"}
    # A second engine reads the cache: pnnx does not run, nothing is said.
    owner = cached_copy(net, tmp_path)
    monkeypatch.setattr(ncnn_module, "converted", no_conversion)
    again = ncnn_engine(net.backbone, owner, ONE_THREAD, say=pytest.fail)
    assert again.description.startswith("ncnn ") and "float32, 1 threads" in again.description


def garbage(path: Path, other: Path) -> None:
    path.write_bytes(b"not an ncnn file")


def truncated(path: Path, other: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def removed(path: Path, other: Path) -> None:
    path.unlink()


def of_other_weights(path: Path, other: Path) -> None:
    """The other network's file in its place, the record rewritten to match it: only
    the torch check can tell."""
    shutil.copyfile(other, path)
    record_path = path.with_name(path.name.rsplit(".", 1)[0] + ".json")
    record = json.loads(record_path.read_text())
    record[f"{path.suffix[1:]}_sha256"] = ncnn_module.hash_of(path)
    record_path.write_text(json.dumps(record))


DAMAGES = {
    ("bin", "garbage"): (garbage, "its files are not the ones converted"),
    ("param", "truncated"): (truncated, "its files are not the ones converted"),
    ("json", "removed"): (removed, "it cannot be read"),
    ("json", "garbage"): (garbage, "it cannot be read"),
    ("bin", "of other weights"): (of_other_weights, "differ from torch's"),
}


@pytest.mark.parametrize("kind", ["full", "maps"])
@pytest.mark.parametrize("damage", DAMAGES, ids=[" ".join(d) for d in DAMAGES])
def test_cached_files_that_cannot_serve_are_converted_again(
    converted, images, tmp_path, kind, damage
):
    net, other = converted("head"), converted("head", seed=1)
    owner = cached_copy(net, tmp_path)
    part, _ = damage
    harm, reason = DAMAGES[damage]
    harm(ncnn_files(owner, KINDS[kind])[part], ncnn_files(other.owner, KINDS[kind])[part])
    notes = []
    engine = ncnn_engine(net.backbone, owner, ONE_THREAD, say=notes.append)
    (note,) = notes
    assert note.startswith(f"note: rebuilt {ncnn_files(owner, KINDS[kind])['param']}: ")
    assert reason in note
    # The files written are whole again: the next engine reads them without a note.
    ncnn_engine(net.backbone, owner, ONE_THREAD, say=pytest.fail)
    torch_way = Relocalizer(
        net.backbone, KMeansIndex(k=3), CentreCrop(), QueryOptions(scoring="shared")
    )
    torch_way.fit(images.map)
    engine_way = torch_way.replace(backbone=engine)
    for image in images.queries:
        assert_same_answer(engine_way.localize(image), torch_way.localize(image))


def test_files_converted_from_another_graph_are_converted_again(converted, tmp_path):
    net, other = converted("head"), converted("head", seed=1)
    owner = cached_copy(net, tmp_path)
    notes = []
    # The other network's ONNX graphs are exported afresh (a note each) and the ncnn
    # files, converted from the first network's graphs, follow them.
    ncnn_engine(other.backbone, owner, ONE_THREAD, say=notes.append)
    ncnn_notes = [n for n in notes if ".ncnn.param" in n]
    assert len(ncnn_notes) == 2
    assert all("it was converted from another ONNX graph" in n for n in ncnn_notes)


def test_a_failed_conversion_names_the_file_and_caches_nothing(tmp_path, monkeypatch):
    def fails(*args, **kwargs):
        raise DataError("pnnx exited with 1: unsupported operator")

    monkeypatch.setattr(ncnn_module, "converted", fails)
    relocalizer = Relocalizer(tiny_posenet(), ExhaustiveIndex(), CentreCrop())
    owner = tmp_path / "net.pt"
    param = ncnn_files(owner, KINDS["full"])["param"]
    message = f"{param}: converting the full graph for ncnn failed: pnnx exited with 1"
    with pytest.raises(EngineUnavailableError, match=message):
        ncnn_engine(relocalizer.backbone, owner, ONE_THREAD, say=pytest.fail)
    assert not list(tmp_path.glob("*.ncnn.*"))
    # Asked for by name, the engine is not replaced by torch: one error.
    with pytest.raises(ConfigError, match=rf"^engine=ncnn cannot run: {param}: converting"):
        on_engine(engine_config("ncnn"), relocalizer, owner, torch.device("cpu"))


@pytest.mark.parametrize("package", ["ncnn", "pnnx", "onnxruntime"])
def test_without_a_package_the_error_names_the_extra(tmp_path, monkeypatch, package):
    monkeypatch.setitem(sys.modules, package, None)  # `import package` fails
    relocalizer = Relocalizer(tiny_posenet(), ExhaustiveIndex(), CentreCrop())
    with pytest.raises(EngineUnavailableError, match=rf"needs '{package}'.*relocfw\[ncnn\]"):
        ncnn_engine(relocalizer.backbone, tmp_path / "net.pt", ONE_THREAD)
    with pytest.raises(ConfigError, match=rf"^engine=ncnn cannot run: .*needs '{package}'"):
        on_engine(engine_config("ncnn"), relocalizer, tmp_path / "net.pt", torch.device("cpu"))
    assert list(tmp_path.iterdir()) == []


def test_on_engine_runs_ncnn_when_asked(converted, images, capsys):
    net = converted("head")
    relocalizer = Relocalizer(net.backbone, KMeansIndex(k=3), CentreCrop())
    relocalizer.fit(images.map)
    cfg = engine_config("ncnn")
    swapped = on_engine(cfg, relocalizer, net.owner, torch.device("cpu"))
    assert all(isinstance(s, NcnnSession) for s in swapped.backbone.sessions.values())
    assert capsys.readouterr().out.splitlines() == ["engine: " + swapped.backbone.description]
    for image in images.queries:
        assert_same_answer(swapped.localize(image), relocalizer.localize(image))


@pytest.mark.parametrize(
    ("int8", "device", "message"),
    [
        ("none", "cuda", "engine=ncnn runs the network with ncnn on the CPU, but device=cuda"),
        ("static", "cpu", "onnx.int8=static quantises onnxruntime's graphs, but engine=ncnn"),
        ("spin", "cpu", "onnx.spinning=true sets onnxruntime's threads, but engine=ncnn"),
    ],
    ids=["on a GPU", "with int8", "with spinning"],
)
def test_wanted_engine_refuses_ncnn_where_it_cannot_run(int8, device, message):
    cfg = engine_config("ncnn", "none" if int8 == "spin" else int8)
    cfg.onnx.spinning = int8 == "spin"
    with pytest.raises(ConfigError, match=message):
        wanted_engine(cfg, torch.device(device))
    assert wanted_engine(engine_config("ncnn"), torch.device("cpu")) == "ncnn"


@pytest.mark.parametrize("options", [{"int8": "dynamic"}, {"spinning": True}])
def test_onnxruntime_options_are_refused_by_the_engine_itself(tmp_path, options):
    with pytest.raises(EngineUnavailableError, match="onnx.spinning are onnxruntime's"):
        ncnn_engine(tiny_posenet(), tmp_path / "net.pt", EngineOptions(**options))


def test_a_network_whose_first_layer_works_in_place_answers_as_torch(images, tmp_path):
    """EfficientNet-Lite0 scales its input in place in ncnn's first layer; ncnn
    crashed the process on a Mat over numpy's memory until the input was copied."""
    pytest.importorskip("efficientnet_lite_pytorch", reason="relocfw[efficientnet] not installed")
    from relocfw.plugins.efficientnet_lite import EfficientNetLite0

    torch.manual_seed(0)
    backbone = EfficientNetLite0(input_size=64, feature_dim=32, pretrained=False).eval()
    backbone.set_crop_scale(1.142857)
    engine = ncnn_engine(backbone, tmp_path / "net.pt", ONE_THREAD, say=pytest.fail)
    torch_way = Relocalizer(backbone, KMeansIndex(k=3), CentreCrop())
    features = torch_way.fit(images.map)
    engine_way = torch_way.replace(backbone=engine)
    np.testing.assert_allclose(engine_way.describe(images.map), features, rtol=0, atol=TOLERANCE)
    for image in images.queries:
        assert_same_answer(engine_way.localize(image), torch_way.localize(image))


def test_a_network_that_crashes_ncnn_is_refused_not_suffered(tmp_path, monkeypatch):
    """The probe run is a process of its own: a crash there (here a stand-in that
    dies of SIGSEGV) becomes one error naming the file, and nothing is cached."""
    crashing = tmp_path / "crashing-python"
    crashing.write_text("#!/bin/sh\nkill -SEGV $$\n")
    crashing.chmod(0o755)
    monkeypatch.setattr(ncnn_module.sys, "executable", str(crashing))
    owner = tmp_path / "run" / "net.pt"
    param = ncnn_files(owner, KINDS["full"])["param"]
    message = f"{param}: converting .* ncnn crashed \\(SIGSEGV\\) running the converted network"
    with pytest.raises(EngineUnavailableError, match=message):
        ncnn_engine(tiny_posenet(), owner, ONE_THREAD, say=pytest.fail)
    assert not list(owner.parent.glob("*.ncnn.*"))


def test_files_of_other_ncnn_versions_are_converted_again(converted, tmp_path):
    net = converted("head")
    owner = cached_copy(net, tmp_path)
    record_path = ncnn_files(owner, KINDS["full"])["json"]
    record = json.loads(record_path.read_text())
    record["versions"]["ncnn"] = "1.0.20200101"
    record_path.write_text(json.dumps(record))
    notes = []
    ncnn_engine(net.backbone, owner, ONE_THREAD, say=notes.append)
    (note,) = notes
    assert "it was converted with other ncnn / pnnx versions" in note


def not_ncnn_layers(path: Path, other: Path) -> None:
    """A .param ncnn cannot read, the record rewritten to match it: only ncnn's own
    load can tell."""
    path.write_text("7767517\n1 1\nNoSuchLayer x 0 1 in0\n")
    record_path = path.with_name(path.name.rsplit(".", 1)[0] + ".json")
    record = json.loads(record_path.read_text())
    record["param_sha256"] = ncnn_module.hash_of(path)
    record_path.write_text(json.dumps(record))


def test_files_ncnn_cannot_load_are_converted_again(converted, tmp_path):
    net = converted("head")
    owner = cached_copy(net, tmp_path)
    files = ncnn_files(owner, KINDS["full"])
    not_ncnn_layers(files["param"], files["param"])
    notes = []
    ncnn_engine(net.backbone, owner, ONE_THREAD, say=notes.append)
    (note,) = notes
    assert note == (
        f"note: rebuilt {files['param']}: the converted network failed its probe run: "
        "ncnn cannot read its layers (.param)"
    )


def test_unusable_files_and_a_failed_conversion_say_both_and_are_removed(
    converted, tmp_path, monkeypatch
):
    def fails(*args, **kwargs):
        raise DataError("pnnx exited with 1: unsupported operator")

    net = converted("head")
    owner = cached_copy(net, tmp_path)
    files = ncnn_files(owner, KINDS["full"])
    files["json"].write_text("{")
    monkeypatch.setattr(ncnn_module, "converted", fails)
    with pytest.raises(EngineUnavailableError) as raised:
        ncnn_engine(net.backbone, owner, ONE_THREAD, say=pytest.fail)
    assert str(raised.value) == (
        f"{files['param']}: converting the full graph for ncnn failed: pnnx exited with 1: "
        "unsupported operator; the cached files were unusable too (it cannot be read "
        "(JSONDecodeError)) and are removed"
    )
    assert not any(path.exists() for path in files.values())


def test_a_probe_run_that_fails_says_why_in_one_line(tmp_path, monkeypatch):
    failing = tmp_path / "failing-python"
    failing.write_text(
        "#!/bin/sh\necho 'Traceback' >&2\necho 'its answers are not finite' >&2\nexit 1\n"
    )
    failing.chmod(0o755)
    monkeypatch.setattr(ncnn_module.sys, "executable", str(failing))
    owner = tmp_path / "run" / "net.pt"
    with pytest.raises(
        EngineUnavailableError, match="failed its probe run: its answers are not finite$"
    ):
        ncnn_engine(tiny_posenet(), owner, ONE_THREAD, say=pytest.fail)


def test_the_probe_imports_neither_relocfw_nor_torch():
    """It runs as a script so that it starts fast and stands alone: its imports are
    the standard library's, numpy's and ncnn's only."""
    tree = ast.parse(Path(ncnn_module.PROBE).read_text())
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            imported.add((node.module or "").split(".")[0])
    assert imported <= {"__future__", "sys", "collections", "pathlib", "numpy", "ncnn"}
