"""engine=onnx (relocfw.model.onnx_engine): every query path answers as torch does,
a cached graph that cannot serve is rebuilt, and torch runs, with one line saying
why, when the engine cannot.

The graphs of each tiny network are exported once for the module (`built`); tests
that damage a cache work on copies of them.
"""

import hashlib
import logging
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from torch import nn

from relocfw.app.engines import (
    keep_graphs_beside,
    on_engine,
    quiet_quantisation,
    wanted_engine,
)
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import orientation_error_deg
from relocfw.core.pipeline import Relocalizer
from relocfw.core.query_options import QueryOptions
from relocfw.model import cpu_flags
from relocfw.model import onnx_engine as engine_module
from relocfw.model.model_file import load_model, save_model
from relocfw.model.onnx_backbone import OnnxBackbone, trained_network
from relocfw.model.onnx_engine import (
    INT8_RECIPES,
    STATIC_MODES,
    EngineOptions,
    EngineUnavailableError,
    adopt_shipped_graphs,
    cgroup_cpu_quota,
    graph_home,
    graph_path,
    onnx_engine,
)
from relocfw.model.onnx_export import WEIGHTS_KEY, weights_fingerprint
from relocfw.model.onnx_graphs import KINDS, kinds_needed
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop

# relocfw imports neither package until it needs one, so the skips can follow the imports.
onnx = pytest.importorskip("onnx", reason='onnx not installed (pip install "relocfw[onnx]")')
pytest.importorskip("onnxruntime", reason='onnxruntime not installed ("relocfw[onnx]")')

TOLERANCE = 1e-4
VARIANTS = ("head", "kendall", "all")
# One thread: the tests' networks are tiny, and the machine may be shared.
ONE_THREAD = EngineOptions(threads=1)
NETWORK = {"input_size": 64, "width": 0.25, "feature_dim": 32}


def tiny_posenet(seed: int = 0, variant: str = "head") -> PoseNet:
    torch.manual_seed(seed)
    backbone = PoseNet(**NETWORK, dropout_variant=variant).eval()
    # torch's default initialisation shrinks the maps to ~1e-5 by the last block, below
    # what any check can tell apart; 0.8 of He's keeps them near 1 (and the "all"
    # variant's samples, which double what dropout keeps at every block, near 10), so
    # answers differ from image to image and from network to network.
    with torch.no_grad():
        for module in backbone.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, nonlinearity="relu").mul_(0.8)
    # A frame away from the origin, so the graphs' positions are mapped back too.
    backbone.set_position_normalisation(np.array([1.0, -2.0, 3.0]), 2.5)
    backbone.set_crop_scale(1.142857)  # > 1: crop_samples has room to draw windows
    return backbone


@dataclass(frozen=True)
class Images:
    map: list[np.ndarray]
    queries: list[np.ndarray]


def seeded_images() -> Images:
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (60, 80, 3), dtype=np.uint8) for _ in range(8)]
    return Images(frames[:6], frames[6:])


@pytest.fixture(scope="module")
def images() -> Images:
    return seeded_images()


@dataclass(frozen=True)
class Built:
    """A tiny network, its engine and the owner its graphs are cached beside."""

    backbone: PoseNet
    engine: OnnxBackbone
    owner: Path


def engines_made_once(tmp_path_factory, make_engine, name: str):
    """get(variant, seed): a tiny network and its engine by `make_engine(backbone,
    owner, options, say)`, made once per (variant, seed) and module, saying nothing."""
    made = {}

    def get(variant: str = "head", seed: int = 0) -> Built:
        if (variant, seed) not in made:
            owner = tmp_path_factory.mktemp(f"{name}-{variant}-{seed}") / "net.pt"
            backbone = tiny_posenet(seed, variant)
            notes = []
            engine = make_engine(backbone, owner, ONE_THREAD, say=notes.append)
            assert notes == []
            made[variant, seed] = Built(backbone, engine, owner)
        return made[variant, seed]

    return get


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """built(variant, seed): the network's engine, its graphs exported once a module."""
    return engines_made_once(tmp_path_factory, onnx_engine, "onnx")


def cached_copy(net: Built, folder: Path) -> Path:
    """A new owner in `folder` with copies of `net`'s cached graphs beside it."""
    owner = folder / "net.pt"
    for kind in kinds_needed(net.backbone):
        shutil.copyfile(graph_path(net.owner, kind), graph_path(owner, kind))
    return owner


class CountedSession:
    """An onnxruntime session that counts its runs (which graphs a query used)."""

    def __init__(self, session) -> None:
        self.session = session
        self.runs = 0

    def run(self, *args, **kwargs):
        self.runs += 1
        return self.session.run(*args, **kwargs)


def count_runs(engine: OnnxBackbone, monkeypatch) -> dict[str, CountedSession]:
    counted = {kind: CountedSession(session) for kind, session in engine.sessions.items()}
    for kind, session in counted.items():
        monkeypatch.setitem(engine.sessions, kind, session)
    return counted


def assert_same_answer(got, want) -> None:
    assert got.crop == want.crop
    assert got.evaluations == want.evaluations
    np.testing.assert_allclose(got.pose.position, want.pose.position, rtol=0, atol=TOLERANCE)
    np.testing.assert_allclose(got.pose.quaternion, want.pose.quaternion, rtol=0, atol=TOLERANCE)
    # NaN (not sampled) matches NaN only. The orientation spread is compared in
    # radians: it is the mean of 2 acos(|<q, mean>|), which at a spread of a few degrees
    # magnifies the quaternions' float32 rounding (~3e-8) some 50 times, ~1e-4 degrees.
    spreads = [got.position_spread, np.radians(got.orientation_spread_deg)]
    wanted = [want.position_spread, np.radians(want.orientation_spread_deg)]
    np.testing.assert_allclose(spreads, wanted, rtol=0, atol=TOLERANCE)


def assert_answers_as_torch(backbone, engine, images, options=None, search=None) -> None:
    """The engine's map and queries are torch's (GA search, shared scoring by default:
    the full and maps graphs both answer)."""
    options = options or QueryOptions(scoring="shared")
    torch_way = Relocalizer(
        backbone, KMeansIndex(k=3), search or GeneticCropSearch(seed=0), options
    )
    features = torch_way.fit(images.map)
    engine_way = torch_way.replace(backbone=engine)
    np.testing.assert_allclose(engine_way.describe(images.map), features, rtol=0, atol=TOLERANCE)
    for image in images.queries:
        assert_same_answer(engine_way.localize(image), torch_way.localize(image))


# case -> (search, query options, backbone.mc_samples)
PATHS = {
    "plain centre": (CentreCrop, {}, 0),
    "plain ga": (lambda: GeneticCropSearch(seed=0), {}, 0),
    "plain sweep": (lambda: SweepCrop(stride=4), {}, 0),
    "shared ga": (lambda: GeneticCropSearch(seed=0), {"scoring": "shared"}, 0),
    "shared sweep": (lambda: SweepCrop(stride=4), {"scoring": "shared", "rerank": 2}, 0),
    "crop samples": (CentreCrop, {"crop_samples": 3}, 0),
    "mc": (CentreCrop, {}, 5),
    "mc ga shared": (lambda: GeneticCropSearch(seed=0), {"scoring": "shared"}, 4),
    "crop samples + mc": (lambda: GeneticCropSearch(seed=0), {"crop_samples": 3}, 4),
}
SAMPLED = ("mc", "mc ga shared", "crop samples + mc")
QUERY_PATHS = [
    pytest.param(variant, case, id=f"{variant}-{case}")
    for case in PATHS
    for variant in (VARIANTS if case in SAMPLED else ("head",))
]


@pytest.mark.parametrize(("variant", "case"), QUERY_PATHS)
def test_each_query_path_answers_as_torch(built, images, monkeypatch, variant, case):
    make_search, options, mc_samples = PATHS[case]
    net = built(variant)
    monkeypatch.setattr(net.backbone, "mc_samples", mc_samples)
    torch_way = Relocalizer(net.backbone, KMeansIndex(k=3), make_search(), QueryOptions(**options))
    features = torch_way.fit(images.map)
    runs = count_runs(net.engine, monkeypatch)
    engine_way = torch_way.replace(backbone=net.engine)
    assert engine_way.index is torch_way.index
    np.testing.assert_allclose(engine_way.describe(images.map), features, rtol=0, atol=TOLERANCE)
    for image in images.queries:
        want, got = torch_way.localize(image), engine_way.localize(image)
        assert_same_answer(got, want)
        if mc_samples or options.get("crop_samples"):
            assert np.isfinite(got.position_spread) and got.orientation_spread_deg > 0
    # The graphs answered (not the source's torch layers).
    used = {kind for kind, session in runs.items() if session.runs}
    assert "full" in used
    if options.get("scoring") == "shared" or (mc_samples and variant != "all"):
        assert "maps" in used
    if mc_samples and variant == "all":
        assert "lower" in used  # the layers below every dropout
    assert net.backbone.mc_samples == mc_samples  # sampling put the count back


def test_queries_localized_together_share_the_graphs_passes(built, images):
    net = built("head")
    torch_way = Relocalizer(net.backbone, KMeansIndex(k=3), GeneticCropSearch(seed=0))
    torch_way.fit(images.map)
    engine_way = torch_way.replace(backbone=net.engine)
    together = engine_way.localize_many(images.queries, queries_at_once=2)
    for got, image in zip(together, images.queries, strict=True):
        assert_same_answer(got, torch_way.localize(image))


@pytest.mark.parametrize("mc_samples", [0, 5], ids=["dropout-free", "mc"])
@pytest.mark.parametrize("variant", VARIANTS)
def test_the_map_is_described_as_torch_describes_it(
    built, images, monkeypatch, variant, mc_samples
):
    net = built(variant)
    monkeypatch.setattr(net.backbone, "mc_samples", mc_samples)  # the map is dropout-free
    torch_way = Relocalizer(net.backbone, ExhaustiveIndex(), CentreCrop())
    want = torch_way.describe(images.map)
    got = torch_way.replace(backbone=net.engine).describe(images.map)
    assert got.shape == want.shape == (6, 32)
    np.testing.assert_allclose(got, want, rtol=0, atol=TOLERANCE)


@pytest.mark.parametrize(
    ("variant", "kinds"),
    [("head", ["full", "maps"]), ("kendall", ["full", "maps"]), ("all", ["full", "lower", "maps"])],
)
def test_the_graphs_a_variant_needs_are_cached_beside_the_owner(built, variant, kinds):
    net = built(variant)
    assert sorted(net.engine.sessions) == kinds
    names = sorted(p.name for p in net.owner.parent.iterdir())
    assert names == sorted(f"net.pt-{kind}.onnx" for kind in kinds)  # no temporary left
    assert net.engine.source is net.backbone
    assert net.engine.description.endswith("float32, 1 threads")
    assert net.engine.description.startswith("onnxruntime ")


def test_an_engine_of_an_engine_runs_the_same_source_from_the_cache(built):
    net = built("head")
    notes = []
    again = onnx_engine(net.engine, net.owner, ONE_THREAD, say=notes.append)
    assert notes == []
    assert again.source is net.backbone and trained_network(again) is net.backbone


def test_an_onnx_backbone_needs_the_full_graph(built):
    net = built("head")
    with pytest.raises(ValueError, match="full graph"):
        OnnxBackbone(net.backbone, {"maps": net.engine.sessions["maps"]}, "maps only")


def garbage(data: bytes, other: bytes) -> bytes:
    return np.random.default_rng(0).integers(0, 256, len(data), dtype=np.uint8).tobytes()


def garbled_weights(data: bytes, other: bytes) -> bytes:
    """A span in the middle overwritten: the file still starts as a graph."""
    middle, span = len(data) // 2, min(4096, len(data) // 4)
    noise = np.random.default_rng(1).integers(0, 256, span, dtype=np.uint8).tobytes()
    return data[:middle] + noise + data[middle + span :]


def truncated(data: bytes, other: bytes) -> bytes:
    return data[: len(data) // 2]


def of_other_weights(data: bytes, other: bytes) -> bytes:
    return other


DAMAGES = {
    "garbage": (garbage, "it cannot be read"),
    "garbled weights": (garbled_weights, "the {kind} graph's"),  # caught by the check
    "truncated": (truncated, "it cannot be read"),
    "stale": (of_other_weights, "it was exported from other weights"),
}


@pytest.mark.parametrize("kind", ["full", "maps"])
@pytest.mark.parametrize("damage", DAMAGES)
def test_a_cached_graph_that_cannot_serve_is_rebuilt(built, images, tmp_path, damage, kind):
    net, other = built("head"), built("head", seed=1)
    owner = cached_copy(net, tmp_path)
    path = graph_path(owner, KINDS[kind])
    spoil, reason = DAMAGES[damage]
    bad = spoil(path.read_bytes(), graph_path(other.owner, KINDS[kind]).read_bytes())
    path.write_bytes(bad)
    notes = []
    engine = onnx_engine(net.backbone, owner, ONE_THREAD, say=notes.append)
    (note,) = notes  # one note, for the spoilt graph only
    assert note.startswith(f"note: rebuilt {path}: {reason.format(kind=kind)}")
    assert path.read_bytes() != bad
    assert sorted(p.name for p in tmp_path.iterdir()) == ["net.pt-full.onnx", "net.pt-maps.onnx"]
    assert_answers_as_torch(net.backbone, engine, images)
    again = []  # the rebuilt file serves from now on
    onnx_engine(net.backbone, owner, ONE_THREAD, say=again.append)
    assert again == []


@pytest.mark.parametrize("kind", ["full", "maps"])
def test_a_graph_whose_metadata_lies_is_caught_by_its_answers(built, images, tmp_path, kind):
    """Network B's fingerprint on network A's graph: only the check against torch on
    seeded images can tell, and the file is rebuilt."""
    net, other = built("head"), built("head", seed=1)
    owner = cached_copy(net, tmp_path)
    path = graph_path(owner, KINDS[kind])
    graph = onnx.load(str(graph_path(other.owner, KINDS[kind])))
    props = {prop.key: prop.value for prop in graph.metadata_props}
    assert props[WEIGHTS_KEY] != weights_fingerprint(net.backbone)
    props[WEIGHTS_KEY] = weights_fingerprint(net.backbone)
    onnx.helper.set_model_props(graph, props)
    onnx.save(graph, str(path))
    lying = path.read_bytes()
    notes = []
    engine = onnx_engine(net.backbone, owner, ONE_THREAD, say=notes.append)
    (note,) = notes
    output = "positions" if kind == "full" else "maps"
    assert note.startswith(f"note: rebuilt {path}: the {kind} graph's {output} differ from torch's")
    assert path.read_bytes() != lying
    assert_answers_as_torch(net.backbone, engine, images)


def engine_config(
    engine: str = "auto", int8: str = "none", quiet: bool = False, threads=1, scoring=None
):
    return OmegaConf.create(
        {
            "engine": engine,
            "onnx": {"threads": threads, "int8": int8, "spinning": False},
            "quiet": quiet,
            "query": {"scoring": scoring},
        }
    )


@pytest.mark.parametrize("package", ["onnxruntime", "onnx"])
def test_without_the_packages_torch_runs_and_one_line_says_why(
    tmp_path, monkeypatch, capsys, package
):
    monkeypatch.setitem(sys.modules, package, None)  # `import package` fails
    relocalizer = Relocalizer(tiny_posenet(), ExhaustiveIndex(), CentreCrop())
    with pytest.raises(EngineUnavailableError, match=rf"needs '{package}'.*relocfw\[onnx\]"):
        onnx_engine(relocalizer.backbone, tmp_path / "net.pt", ONE_THREAD)
    cfg = engine_config(threads=None)
    assert on_engine(cfg, relocalizer, tmp_path / "net.pt", torch.device("cpu")) is relocalizer
    printed = capsys.readouterr()
    assert printed.out == ""  # notes go to stderr, with the CLI's other notes
    (line,) = printed.err.splitlines()
    assert line.startswith("note: ") and f"'{package}'" in line and "runs on torch" in line
    assert list(tmp_path.iterdir()) == []


def test_a_graph_that_fails_the_torch_check_at_export_leaves_torch_running(
    tmp_path, monkeypatch, capsys
):
    def disagree(session, network, kind):
        raise DataError(f"the {kind.name} graph's positions differ from torch's (up to 1)")

    # onnx_engine holds its own reference to onnx_graphs.largest_difference.
    monkeypatch.setattr(engine_module, "largest_difference", disagree)
    relocalizer = Relocalizer(tiny_posenet(), ExhaustiveIndex(), CentreCrop())
    owner = tmp_path / "net.pt"
    with pytest.raises(EngineUnavailableError, match="the full graph's positions differ"):
        onnx_engine(relocalizer.backbone, owner, ONE_THREAD, say=pytest.fail)
    assert on_engine(engine_config("auto"), relocalizer, owner, torch.device("cpu")) is relocalizer
    (line,) = capsys.readouterr().err.splitlines()
    full = graph_path(owner, KINDS["full"])
    assert line.startswith(
        f"note: {full}: exporting the full graph failed: the full graph's positions differ"
    )
    assert line.endswith("the network runs on torch (engine=torch silences this)")
    assert list(tmp_path.iterdir()) == []  # a graph that failed its check is not cached
    # Asked for by name, the engine is not silently replaced: one error naming the file.
    for engine, int8, asked in (("onnx", "none", "engine=onnx"), ("auto", "dynamic", "onnx.int8")):
        with pytest.raises(ConfigError, match=rf"^{asked}.* cannot run: {full}: exporting"):
            on_engine(engine_config(engine, int8), relocalizer, owner, torch.device("cpu"))


@pytest.mark.parametrize("quiet", [False, True])
def test_on_engine_swaps_the_network_and_keeps_the_map(built, images, capsys, quiet):
    net = built("head")
    relocalizer = Relocalizer(net.backbone, KMeansIndex(k=3), GeneticCropSearch(seed=0))
    relocalizer.fit(images.map)
    swapped = on_engine(engine_config(quiet=quiet), relocalizer, net.owner, torch.device("cpu"))
    assert isinstance(swapped.backbone, OnnxBackbone) and swapped.backbone.source is net.backbone
    assert swapped.index is relocalizer.index and swapped.search is relocalizer.search
    printed = capsys.readouterr().out.splitlines()
    assert printed == ([] if quiet else ["engine: " + swapped.backbone.description])
    for image in images.queries:
        assert_same_answer(swapped.localize(image), relocalizer.localize(image))
    # engine=torch leaves the relocalizer as it is, writing and saying nothing.
    assert on_engine(engine_config("torch"), relocalizer, None, torch.device("cpu")) is relocalizer
    assert capsys.readouterr().out == ""


@pytest.mark.parametrize(
    ("engine", "int8", "device", "wanted"),
    [
        ("auto", "none", "cpu", "onnx"),
        ("auto", "none", "cuda", "torch"),
        ("auto", "dynamic", "cpu", "onnx"),
        ("onnx", "static", "cpu", "onnx"),
        ("torch", "none", "cpu", "torch"),
        ("torch", "none", "cuda", "torch"),
    ],
)
def test_wanted_engine(engine, int8, device, wanted):
    assert wanted_engine(engine_config(engine, int8), torch.device(device)) == wanted


@pytest.mark.parametrize(
    ("engine", "int8", "threads", "device", "message"),
    [
        (
            "onnx",
            "none",
            1,
            "cuda",
            "engine=onnx runs the network with onnxruntime on the CPU, but device=cuda",
        ),
        ("torch", "static", 1, "cpu", "onnx.int8=static quantises the onnxruntime graphs"),
        ("torch", "dynamic", 1, "cpu", "onnx.int8=dynamic quantises the onnxruntime graphs"),
        (
            "auto",
            "int4",
            1,
            "cpu",
            "onnx.int8 must be one of none, dynamic, static, static_8bit, got 'int4'",
        ),
        ("torch", "none", 0, "cpu", "onnx.threads must be >= 1"),
        ("auto", "static", 1, "cuda", r"runs on torch here \(device=cuda\)"),
    ],
    ids=[
        "onnx on cuda",
        "static on torch",
        "dynamic on torch",
        "unknown int8",
        "no threads",
        "int8 with auto on a GPU",
    ],
)
def test_wanted_engine_refuses_options_that_cannot_apply(engine, int8, threads, device, message):
    cfg = engine_config(engine, int8, threads=threads)
    with pytest.raises(ConfigError, match=message):
        wanted_engine(cfg, torch.device(device))


def test_int8_dynamic_graphs_are_cached_and_answer(built, images, tmp_path, caplog):
    net = built("head")
    owner = cached_copy(net, tmp_path)  # the float graphs: only quantisation runs
    notes = []
    options = EngineOptions(threads=1, int8="dynamic")
    caplog.set_level(logging.INFO)
    # onnxruntime's quantisation logs a line per weight at INFO, which Hydra would print;
    # the CLI (relocfw.app.engines) silences it while the engine is built.
    with quiet_quantisation():
        engine = onnx_engine(net.backbone, owner, options, say=notes.append)
    assert notes == []
    assert [r.getMessage() for r in caplog.records if r.levelno <= logging.INFO] == []
    assert logging.root.manager.disable == logging.NOTSET  # put back
    assert engine.description.endswith("int8 dynamic, 1 threads")
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "net.pt-full.int8-dynamic.onnx",
        "net.pt-full.onnx",
        "net.pt-maps.int8-dynamic.onnx",
        "net.pt-maps.onnx",
    ]
    torch_way = Relocalizer(
        net.backbone, KMeansIndex(k=3), GeneticCropSearch(seed=0), QueryOptions(scoring="shared")
    )
    features = torch_way.fit(images.map)
    engine_way = torch_way.replace(backbone=engine)
    assert_descriptors_near_float32(engine_way.fit(images.map), features)
    for image in images.queries:
        answer = engine_way.localize(image)
        assert answer.evaluations > 1  # the search ran
        assert_pose_near_float32(answer, torch_way, image)


def test_int8_dynamic_answers_do_not_depend_on_the_batch(built, images, tmp_path):
    """Dynamic quantisation scales a pass by its whole batch: the engine runs one image
    per pass, so queries searched together answer as one at a time."""
    net = built("head")
    owner = cached_copy(net, tmp_path)
    engine = onnx_engine(net.backbone, owner, EngineOptions(threads=1, int8="dynamic"))
    relocalizer = Relocalizer(engine, KMeansIndex(k=3), GeneticCropSearch(seed=0))
    relocalizer.fit(images.map)
    queries = images.queries + images.map[:2]
    alone = [relocalizer.localize(image) for image in queries]
    together = relocalizer.localize_many(queries, queries_at_once=len(queries))
    for got, want in zip(together, alone, strict=True):
        assert got.crop == want.crop
        np.testing.assert_array_equal(got.pose.position, want.pose.position)


def test_int8_static_calibrates_on_map_images_once(built, images, tmp_path):
    net = built("head")
    owner = cached_copy(net, tmp_path)
    options = EngineOptions(threads=1, int8="static")
    with pytest.raises(ConfigError, match="onnx.int8=static calibrates on map images"):
        onnx_engine(net.backbone, owner, options, say=pytest.fail)
    assert not list(tmp_path.glob("*int8*"))
    engine = onnx_engine(net.backbone, owner, options, images.map, say=pytest.fail)
    assert engine.description.endswith("int8 static, 1 threads")
    static = sorted(tmp_path.glob("*.int8-static.onnx"))
    assert [p.name for p in static] == [
        "net.pt-full.int8-static.onnx",
        "net.pt-maps.int8-static.onnx",
    ]
    written = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in static}
    # Cached: no calibration images needed, nothing said, nothing written.
    again = onnx_engine(net.backbone, owner, options, say=pytest.fail)
    assert {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in static} == written
    torch_way = Relocalizer(net.backbone, ExhaustiveIndex(), CentreCrop())
    features = torch_way.fit(images.map)
    engine_way = torch_way.replace(backbone=again)
    assert_descriptors_near_float32(engine_way.describe(images.map), features)
    for image in images.queries:
        assert_pose_near_float32(engine_way.localize(image), torch_way, image)


def test_int8_static_8bit_has_its_own_graphs_and_recipe(built, images, tmp_path, monkeypatch):
    """8-bit weights: quantised without reduce_range, cached beside the 7-bit ones
    (switching between them rebuilds nothing), answering differently from them."""
    monkeypatch.setattr(cpu_flags, "int8_saturation_reason", lambda: None)
    net = built("head")
    owner = cached_copy(net, tmp_path)
    seven = onnx_engine(net.backbone, owner, EngineOptions(threads=1, int8="static"), images.map)
    options = EngineOptions(threads=1, int8="static_8bit")
    eight = onnx_engine(net.backbone, owner, options, images.map, say=pytest.fail)
    assert eight.int8 == "static_8bit"
    path = graph_path(owner, KINDS["full"], "static_8bit")
    assert path.name == "net.pt-full.int8-static_8bit.onnx"
    props = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    assert props["relocfw.int8_recipe"] == INT8_RECIPES["static_8bit"]
    assert "reduce_range" not in props["relocfw.int8_recipe"]
    onnx_engine(net.backbone, owner, EngineOptions(threads=1, int8="static"), say=pytest.fail)
    batch = torch.rand(2, 3, net.backbone.input_size, net.backbone.input_size)
    assert not torch.equal(seven(batch).positions, eight(batch).positions)
    torch_way = Relocalizer(net.backbone, ExhaustiveIndex(), CentreCrop())
    features = torch_way.fit(images.map)
    for engine in (seven, eight):
        described = torch_way.replace(backbone=engine).describe(images.map)
        assert_descriptors_near_float32(described, features)


def cpuinfo_with(tmp_path: Path, flags: str) -> Path:
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text(f"processor\t: 0\nflags\t\t: {flags}\n")
    return cpuinfo


@pytest.mark.parametrize(
    ("machine", "flags", "refused"),
    [
        ("x86_64", "fpu sse avx2 fma", "no VNNI"),
        ("x86_64", "fpu avx2 avx512f avx512_vnni", None),
        ("x86_64", "fpu avx2 avx_vnni", None),
        ("x86_64", "fpu avx512f amx_int8", None),
        ("x86_64", None, "cannot read this CPU's flags"),
        ("AMD64", "fpu sse avx2", "no VNNI"),
        ("arm64", None, None),
        ("aarch64", "fp asimd", None),
    ],
)
def test_8bit_weights_are_refused_where_products_may_saturate(
    tmp_path, monkeypatch, machine, flags, refused
):
    monkeypatch.setattr(cpu_flags.platform, "machine", lambda: machine)
    cpuinfo = cpuinfo_with(tmp_path, flags) if flags else tmp_path / "missing"
    why = cpu_flags.int8_saturation_reason(cpuinfo)
    if refused is None:
        assert why is None
        return
    assert refused in why and "use onnx.int8=static" in why
    monkeypatch.setattr(cpu_flags, "int8_saturation_reason", lambda: why)
    options = EngineOptions(threads=1, int8="static_8bit")
    with pytest.raises(EngineUnavailableError, match=refused):
        onnx_engine(PoseNet(32, width=0.25), tmp_path / "net.pt", options)
    # The CLI refuses it before any work (task=compare checks every row up front).
    with pytest.raises(ConfigError, match=f"onnx.int8=static_8bit cannot run here: .*{refused}"):
        wanted_engine(engine_config("auto", "static_8bit"), torch.device("cpu"))


def test_a_static_graph_is_remade_when_its_float_graph_changes(built, images, tmp_path):
    net = built("head")
    owner = cached_copy(net, tmp_path)
    options = EngineOptions(threads=1, int8="static")
    onnx_engine(net.backbone, owner, options, images.map, say=pytest.fail)
    static = graph_path(owner, KINDS["full"], "static")
    before = static.read_bytes()
    # Another float graph of the same weights (as a new exporter would write): the
    # int8 graph made from the old one must not serve it.
    full = graph_path(owner, KINDS["full"])
    graph = onnx.load(str(full))
    graph.doc_string = "exported again"
    onnx.save(graph, str(full))
    notes = []
    onnx_engine(net.backbone, owner, options, images.map, say=notes.append)
    assert notes == [f"note: rebuilt {static}: it was quantised from another float graph"]
    assert static.read_bytes() != before


@pytest.mark.parametrize("mode", STATIC_MODES)
def test_relocalize_keeps_static_graphs_beside_the_model_file(
    built, images, tmp_path, monkeypatch, mode
):
    """task=localize has no map images to calibrate on: the model file's folder must
    hold the static graphs task=relocalize made (of the mode it ran, and no other)."""
    monkeypatch.setattr(cpu_flags, "int8_saturation_reason", lambda: None)
    net = built("head")
    (tmp_path / "cache").mkdir()
    checkpoint = cached_copy(net, tmp_path / "cache")
    other = next(m for m in STATIC_MODES if m != mode)
    onnx_engine(net.backbone, checkpoint, EngineOptions(threads=1, int8=other), images.map)
    options = EngineOptions(threads=1, int8=mode)
    engine = onnx_engine(net.backbone, checkpoint, options, images.map, say=pytest.fail)
    relocalizer = Relocalizer(engine, ExhaustiveIndex(), CentreCrop())
    model = tmp_path / "run" / "model.relocfw"
    model.parent.mkdir()
    keep_graphs_beside(relocalizer, checkpoint, model)
    beside = sorted(p.name for p in model.parent.iterdir())
    assert beside == sorted(
        f"model.relocfw-{kind}{suffix}.onnx"
        for kind in ("full", "maps")
        for suffix in ("", f".int8-{mode}")
    )
    reused = onnx_engine(net.backbone, model, options, say=pytest.fail)  # no calibration
    assert reused.int8 == mode
    # A float engine keeps nothing beside the model file: its graphs can be remade.
    keep_graphs_beside(relocalizer.replace(backbone=net.engine), checkpoint, tmp_path / "m2")
    assert not list(tmp_path.glob("m2*"))


class CountedImages:
    """A session that counts the images it runs (which windows went through it)."""

    def __init__(self, session) -> None:
        self.session = session
        self.images = 0

    def run(self, names, feeds):
        self.images += len(next(iter(feeds.values())))
        return self.session.run(names, feeds)


def scout_engine(built, images, folder: Path) -> tuple[Built, OnnxBackbone]:
    net = built("head")
    owner = cached_copy(net, folder)
    options = EngineOptions(threads=1, int8="static", scout=True)
    return net, onnx_engine(net.backbone, owner, options, images.map, say=pytest.fail)


def test_an_int8_scout_ranks_and_the_float32_graphs_answer(built, images, tmp_path, monkeypatch):
    net, engine = scout_engine(built, images, tmp_path)
    assert engine.description.endswith("float32, int8 static scout, 1 threads")
    # Only the full graph is quantised: every other pass runs float32.
    assert [p.name for p in tmp_path.glob("*int8*")] == ["net.pt-full.int8-static.onnx"]
    torch_way = Relocalizer(net.backbone, KMeansIndex(k=3), GeneticCropSearch(seed=0))
    torch_way.fit(images.map)
    scouted = torch_way.replace(backbone=engine, options=QueryOptions(scoring="scout"))
    full = CountedImages(engine.sessions["full"])
    scout = CountedImages(engine.scout)
    monkeypatch.setitem(engine.sessions, "full", full)
    monkeypatch.setattr(engine, "scout", scout)
    windows = 0
    for image in images.queries:
        answer = scouted.localize(image)
        windows += answer.evaluations
        strip = torch_way.scorer.strip(image)
        window = strip.cut(strip.window(answer.crop))[None]
        exact = torch_way.scorer.forward(window)
        np.testing.assert_allclose(answer.pose.position, exact.positions[0], atol=TOLERANCE)
        np.testing.assert_allclose(answer.pose.quaternion, exact.quaternions[0], atol=TOLERANCE)
        # The scout is the int8 graph: its descriptors are not the float32 ones.
        with torch.inference_mode():
            rounded = engine.scout_features(window.float() / 255).numpy()
        assert np.abs(rounded - exact.features).max() > 1e-3
        assert_descriptors_near_float32(rounded, exact.features)
    # Every distinct window once through the scout (the 2 checks above included);
    # the float32 graph ran once per query, on its chosen crop.
    assert scout.images == windows + len(images.queries)
    assert full.images == len(images.queries)


def test_an_int8_scouts_scores_do_not_depend_on_the_batch(built, images, tmp_path):
    """Static int8 scales are fixed: a query's windows score as they would alone, so
    queries searched together answer as one at a time (dynamic ones would not)."""
    net, engine = scout_engine(built, images, tmp_path)
    scouted = Relocalizer(
        engine, KMeansIndex(k=3), GeneticCropSearch(seed=0), QueryOptions(scoring="scout")
    )
    scouted.fit(images.map)
    queries = images.queries + images.map[:2]
    alone = [scouted.localize(image) for image in queries]
    together = scouted.localize_many(queries, queries_at_once=len(queries))
    for got, want in zip(together, alone, strict=True):
        assert_same_answer(got, want)


def test_an_int8_engine_without_its_scout_is_refused_for_scout_scoring(built, images, tmp_path):
    net = built("head")
    owner = cached_copy(net, tmp_path)
    throughout = onnx_engine(
        net.backbone, owner, EngineOptions(threads=1, int8="static"), images.map
    )
    options = QueryOptions(scoring="scout")
    with pytest.raises(ConfigError, match="scoring=scout: the engine's graphs are int8 static"):
        Relocalizer(throughout, KMeansIndex(k=3), GeneticCropSearch(seed=0), options)


def test_scout_scoring_needs_onnxruntimes_static_int8_graphs(built, images):
    for int8 in ("none", "dynamic"):
        with pytest.raises(ConfigError, match="query.scoring=scout .* set onnx.int8=static"):
            EngineOptions(scout=True, int8=int8)
    refusals = [
        ("torch", "static", "cpu", "but the network runs on torch here"),
        ("auto", "static", "cuda", "but the network runs on torch here"),
        ("ncnn", "none", "cpu", "but the network runs on engine=ncnn here"),
        ("auto", "none", "cpu", "scores candidate crops with the static int8 graph"),
        ("onnx", "dynamic", "cpu", "not onnx.int8=dynamic"),
    ]
    for engine, int8, device, message in refusals:
        with pytest.raises(ConfigError, match=message):
            wanted_engine(engine_config(engine, int8, scoring="scout"), torch.device(device))
    cfg = engine_config("auto", "static", scoring="scout")
    assert wanted_engine(cfg, torch.device("cpu")) == "onnx"
    # A model file's scoring (task=localize) is checked too, and said to be the file's.
    net = built("head")
    options = QueryOptions(scoring="scout")
    relocalizer = Relocalizer(net.backbone, ExhaustiveIndex(), CentreCrop(), options)
    with pytest.raises(ConfigError, match=r"set onnx.int8=static.*is the model file's\)$"):
        on_engine(engine_config("auto"), relocalizer, net.owner, torch.device("cpu"))
    with pytest.raises(ConfigError, match=r"runs on torch here.*is the model file's\)$"):
        on_engine(engine_config("torch"), relocalizer, net.owner, torch.device("cpu"))


@pytest.mark.parametrize(
    ("text", "cores"), [("200000 100000\n", 2), ("150000 100000", 1), ("max 100000", None)]
)
def test_a_container_cpu_quota_caps_the_threads(tmp_path, text, cores):
    quota = tmp_path / "cpu.max"
    quota.write_text(text)
    assert cgroup_cpu_quota(quota) == cores
    assert cgroup_cpu_quota(tmp_path / "absent") is None


def test_a_model_file_of_an_engine_relocalizer_holds_the_torch_network(built, images, tmp_path):
    net = built("kendall")
    torch_way = Relocalizer(net.backbone, KMeansIndex(k=3), GeneticCropSearch(seed=0))
    torch_way.fit(images.map)
    engine_way = torch_way.replace(backbone=net.engine)
    options = {
        "backbone": {**NETWORK, "dropout_variant": "kendall"},
        "index": {"k": 3},
        "crop": {"seed": 0},
    }
    path = save_model(tmp_path / "model.relocfw", engine_way, options, {})
    loaded = load_model(path)
    assert type(loaded.backbone) is PoseNet
    want, got = net.backbone.state_dict(), loaded.backbone.state_dict()
    assert list(got) == list(want)
    for key in want:
        assert torch.equal(got[key], want[key]), key
    assert float(loaded.crop_scale) == pytest.approx(float(net.backbone.crop_scale))
    for image in images.queries:
        assert_same_answer(loaded.localize(image), engine_way.localize(image))


# How far int8 answers may lie from float32's (the int8 checks above). MEASURED on the
# "head" network and seeded images here (x86 AVX2, no VNNI): descriptors 0.027-0.063
# of their length (static 0.027-0.036, dynamic 0.050-0.056, static_8bit 0.050-0.063),
# positions 0.014-0.065, orientations 0.19-0.52 degrees. The bounds are about twice
# the worst. A static graph calibrated on 0-255 pixels instead of 0-1 answers
# descriptors 100% off and orientations 7 degrees off; calibrated on a single map
# image, tests/model/test_int8_calibration.py shows what it costs.
INT8_DESCRIPTOR_DEVIATION = 0.12  # |int8 - float32| / |float32|, per descriptor
INT8_POSITION_DEVIATION = 0.13  # in the network's position units
INT8_ORIENTATION_DEVIATION_DEG = 1.0


def assert_descriptors_near_float32(got: np.ndarray, want: np.ndarray) -> None:
    """Each int8 descriptor within INT8_DESCRIPTOR_DEVIATION of float32's, relative."""
    got, want = np.asarray(got), np.asarray(want)
    deviations = np.linalg.norm(got - want, axis=1) / np.linalg.norm(want, axis=1)
    assert deviations.max() < INT8_DESCRIPTOR_DEVIATION, deviations.round(3)


def assert_pose_near_float32(answer, torch_way: Relocalizer, image: np.ndarray) -> None:
    """An int8 answer's pose near what float32 torch answers for the same crop."""
    strip = torch_way.scorer.strip(image)
    exact = torch_way.scorer.forward(strip.cut(strip.window(answer.crop))[None])
    position = np.linalg.norm(answer.pose.position - exact.positions[0])
    assert position < INT8_POSITION_DEVIATION
    angle = orientation_error_deg(answer.pose.quaternion, exact.quaternions[0])
    assert angle < INT8_ORIENTATION_DEVIATION_DEG


def saved_model(net: Built, images: Images, path: Path) -> Path:
    """A model file of `net` (a centre crop over an exhaustive map) at `path`."""
    relocalizer = Relocalizer(net.backbone, ExhaustiveIndex(), CentreCrop())
    relocalizer.fit(images.map)
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_model(path, relocalizer, {"backbone": NETWORK}, {})


def test_a_model_files_graphs_are_cached_by_its_content_and_never_beside_it(
    built, images, tmp_path, monkeypatch, capsys
):
    """The model file's folder (a robot's may be read-only) gets no file; the graphs go
    to cache_dir/graphs/<its SHA-256>/, and a second load reuses them, exporting none."""
    net = built("head")
    model = saved_model(net, images, tmp_path / "robot" / "model.relocfw")
    cfg = OmegaConf.merge(engine_config(quiet=True), {"cache_dir": str(tmp_path / "cache")})
    first = on_engine(cfg, load_model(model), model, torch.device("cpu"))
    assert isinstance(first.backbone, OnnxBackbone)
    assert sorted(p.name for p in model.parent.iterdir()) == ["model.relocfw"]
    digest = hashlib.sha256(model.read_bytes()).hexdigest()[:16]
    home = tmp_path / "cache" / "graphs" / digest
    graphs = ["model.relocfw-full.onnx", "model.relocfw-maps.onnx"]  # "head": maps too
    assert sorted(p.name for p in home.iterdir()) == graphs
    written = (home / "model.relocfw-full.onnx").stat().st_mtime_ns

    def no_export(*args, **kwargs):
        raise AssertionError("the cached graph was exported again")

    monkeypatch.setattr(engine_module, "graph_bytes", no_export)
    again = on_engine(cfg, load_model(model), model, torch.device("cpu"))
    assert isinstance(again.backbone, OnnxBackbone)
    assert (home / "model.relocfw-full.onnx").stat().st_mtime_ns == written
    assert capsys.readouterr().err == ""
    # Another model file (other content, same name) gets graphs of its own.
    monkeypatch.undo()
    other = saved_model(built("head", seed=1), images, tmp_path / "robot2" / "model.relocfw")
    on_engine(cfg, load_model(other), other, torch.device("cpu"))
    assert len(list((tmp_path / "cache" / "graphs").iterdir())) == 2


def test_graphs_shipped_beside_a_model_file_are_used_from_the_cache(
    built, images, tmp_path, monkeypatch
):
    """Static int8 graphs kept beside a model file by task=relocalize (they cannot be
    remade without map images) serve a later run from the cache, with no calibration."""
    monkeypatch.setattr(cpu_flags, "int8_saturation_reason", lambda: None)
    net = built("head")
    model = saved_model(net, images, tmp_path / "robot" / "model.relocfw")
    options = EngineOptions(threads=1, int8="static")
    onnx_engine(net.backbone, model, options, images.map, say=pytest.fail)  # beside it
    shipped = sorted(p.name for p in model.parent.iterdir())
    cfg = OmegaConf.merge(engine_config(int8="static"), {"cache_dir": str(tmp_path / "cache")})
    engine = on_engine(cfg, load_model(model), model, torch.device("cpu"))  # none at hand
    assert engine.backbone.int8 == "static"
    assert sorted(p.name for p in model.parent.iterdir()) == shipped


def test_graphs_shipped_beside_a_model_file_are_read_there_where_the_cache_is_unwritable(
    built, images, tmp_path, monkeypatch
):
    """A cache that cannot be written (here: its folder's parent is a file) leaves the
    static int8 graphs kept beside the model file where they are, read from there with
    no calibration, instead of a refusal asking for map images."""
    monkeypatch.setattr(cpu_flags, "int8_saturation_reason", lambda: None)
    net = built("head")
    model = saved_model(net, images, tmp_path / "robot" / "model.relocfw")
    options = EngineOptions(threads=1, int8="static")
    onnx_engine(net.backbone, model, options, images.map, say=pytest.fail)  # beside it
    (tmp_path / "blocker").write_text("a file where the cache's parent folder would be")
    cfg = OmegaConf.merge(
        engine_config(int8="static"), {"cache_dir": str(tmp_path / "blocker" / "cache")}
    )
    engine = on_engine(cfg, load_model(model), model, torch.device("cpu"))  # none at hand
    assert engine.backbone.int8 == "static"


def test_a_cached_copy_of_other_bytes_is_replaced_by_the_graph_shipped_beside_the_model(
    built, images, tmp_path, monkeypatch
):
    monkeypatch.setattr(cpu_flags, "int8_saturation_reason", lambda: None)
    net = built("head")
    model = saved_model(net, images, tmp_path / "robot" / "model.relocfw")
    options = EngineOptions(threads=1, int8="static")
    onnx_engine(net.backbone, model, options, images.map, say=pytest.fail)  # beside it
    cache = tmp_path / "cache"
    home = graph_home(model, cache)
    shipped = [path for path in model.parent.iterdir() if path != model]
    assert shipped
    for path in shipped:  # damaged copies in the cache, of the same names
        (home.parent / path.name).write_bytes(b"not a graph")
    assert adopt_shipped_graphs(model, home) == home
    for path in shipped:
        assert (home.parent / path.name).read_bytes() == path.read_bytes()
    cfg = OmegaConf.merge(engine_config(int8="static"), {"cache_dir": str(cache)})
    engine = on_engine(cfg, load_model(model), model, torch.device("cpu"))
    assert engine.backbone.int8 == "static"
