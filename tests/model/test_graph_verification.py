"""Graphs found beside a model or checkpoint are checked by their answers, not their
word (issue 39, item 2): a graph file comes from the same untrusted place as the
model, and its metadata (fingerprints, recipe, source graph) is whatever its writer
put there. Each open runs it and the torch network on fresh real-range images; a
float graph that answers otherwise is rebuilt, an int8 one is refused.

The forgeries are the issue's: the genuine graph with +100 m added to every position
(x), the genuine file's metadata kept or copied in; and one that is genuine except on
the pixels real crops hold (multiples of 1/255), which seeded continuous check images
never show.
"""

import numpy as np
import pytest
import torch

from relocfw.core.errors import DataError
from relocfw.core.imaging import Strip, to_network_input
from relocfw.model import onnx_engine as engine_module
from relocfw.model.onnx_engine import EngineOptions, graph_path, onnx_engine
from relocfw.model.onnx_export import INPUT_NAME
from relocfw.model.onnx_graphs import KINDS

onnx = pytest.importorskip("onnx", reason='onnx not installed (pip install "relocfw[onnx]")')
pytest.importorskip("onnxruntime", reason='onnxruntime not installed ("relocfw[onnx]")')
from onnx import TensorProto, helper  # noqa: E402

from tests.model.test_onnx_engine import (  # noqa: E402
    ONE_THREAD,
    assert_answers_as_torch,
    built,  # noqa: F401 - the module's engines, exported once
    cached_copy,
    images,  # noqa: F401 - the seeded map and query images
)

SHIFT = 100.0  # metres added to x


def forged(graph: onnx.ModelProto, on_real_pixels_only: bool = False) -> onnx.ModelProto:
    """`graph` with SHIFT metres added to every position's x (only for images whose
    pixels are all multiples of 1/255, as a query's are, when `on_real_pixels_only`);
    its metadata is left as it was."""
    nodes = graph.graph.node
    for node in nodes:  # the genuine answer gets another name; the forgery's is "positions"
        node.output[:] = ["genuine" if name == "positions" else name for name in node.output]
        node.input[:] = ["genuine" if name == "positions" else name for name in node.input]
    shift = helper.make_tensor("shift", TensorProto.FLOAT, [1, 3], [SHIFT, 0.0, 0.0])
    graph.graph.initializer.append(shift)
    if not on_real_pixels_only:
        nodes.append(helper.make_node("Add", ["genuine", "shift"], ["positions"]))
        return graph
    for name, value in (("255", 255.0), ("tiny", 1e-3)):
        graph.graph.initializer.append(helper.make_tensor(name, TensorProto.FLOAT, [], [value]))
    nodes.extend(
        [
            helper.make_node("Mul", [INPUT_NAME, "255"], ["levels"]),
            helper.make_node("Round", ["levels"], ["rounded"]),
            helper.make_node("Sub", ["levels", "rounded"], ["off"]),
            helper.make_node("Abs", ["off"], ["off_size"]),
            helper.make_node("ReduceMax", ["off_size"], ["most_off"], axes=[1, 2, 3]),
            helper.make_node("Flatten", ["most_off"], ["most_off_column"], axis=1),
            helper.make_node("Less", ["most_off_column", "tiny"], ["real_pixels"]),
            helper.make_node("Cast", ["real_pixels"], ["switch"], to=TensorProto.FLOAT),
            helper.make_node("Mul", ["switch", "shift"], ["switched_shift"]),
            helper.make_node("Add", ["genuine", "switched_shift"], ["positions"]),
        ]
    )
    return graph


def query_crops(queries: list[np.ndarray], network) -> np.ndarray:
    """The queries' centre crops as the pipeline feeds them (uint8 / 255)."""
    crops = []
    for image in queries:
        strip = Strip(image, int(network.input_size), float(network.crop_scale))
        crops.append(strip.cut(strip.window(strip.centre_crop())))
    return to_network_input(torch.stack(crops)).numpy()


def positions_of(graph: onnx.ModelProto, inputs: np.ndarray) -> np.ndarray:
    import onnxruntime

    session = onnxruntime.InferenceSession(
        graph.SerializeToString(), providers=["CPUExecutionProvider"]
    )
    return session.run(["positions"], {INPUT_NAME: inputs})[0]


@pytest.mark.parametrize("mode", ["static", "dynamic"])
def test_a_forged_int8_graph_is_refused_in_one_line(built, images, tmp_path, mode):  # noqa: F811
    """The issue's forgery: the float graph plus 100 m, with the genuine int8 file's
    metadata copied in. Its word is the genuine file's; its answers are not."""
    net = built("head")
    owner = cached_copy(net, tmp_path)
    options = EngineOptions(threads=1, int8=mode)
    onnx_engine(net.backbone, owner, options, images.map, say=pytest.fail)  # the genuine one
    path = graph_path(owner, KINDS["full"], mode)
    forgery = forged(onnx.load(str(graph_path(owner, KINDS["full"]))))
    del forgery.metadata_props[:]
    forgery.metadata_props.extend(onnx.load(str(path)).metadata_props)
    onnx.save(forgery, str(path))
    crops = query_crops(images.queries, net.backbone)
    with torch.no_grad():
        truth = net.backbone(torch.from_numpy(crops)).positions.numpy()
    np.testing.assert_allclose(positions_of(forgery, crops) - truth, [[SHIFT, 0, 0]] * 2, atol=1e-3)
    written = path.read_bytes()
    # Refused with the map images at hand too: it was tampered with, not made stale.
    for calibration in (None, images.map):
        with pytest.raises(DataError) as refused:
            onnx_engine(net.backbone, owner, options, calibration, say=pytest.fail)
        message = str(refused.value)
        assert "\n" not in message
        assert message.startswith(f"{path}: refused: the int8 full graph's positions lie ")
        assert "remove the file to have it quantised anew" in message
    assert path.read_bytes() == written  # refused, not replaced


@pytest.mark.parametrize("on_real_pixels_only", [False, True], ids=["always", "on real pixels"])
def test_a_forged_float_graph_is_rebuilt_and_answers_as_torch(
    built,  # noqa: F811
    images,  # noqa: F811
    tmp_path,
    on_real_pixels_only,
):
    """The genuine file's own metadata, positions 100 m off: rebuilt with one note. The
    forgery that is genuine on continuous pixels passed the seeded check images before
    (they were torch.rand), and answered every query 100 m off."""
    net = built("head")
    owner = cached_copy(net, tmp_path)
    path = graph_path(owner, KINDS["full"])
    forgery = forged(onnx.load(str(path)), on_real_pixels_only)
    onnx.save(forgery, str(path))
    crops = query_crops(images.queries, net.backbone)
    with torch.no_grad():
        truth = net.backbone(torch.from_numpy(crops)).positions.numpy()
    np.testing.assert_allclose(positions_of(forgery, crops) - truth, [[SHIFT, 0, 0]] * 2, atol=1e-3)
    notes = []
    engine = onnx_engine(net.backbone, owner, ONE_THREAD, say=notes.append)
    assert len(notes) == 1, f"the forged {path.name} was used: notes {notes}"
    assert notes[0].startswith(f"note: rebuilt {path}: the full graph's positions differ")
    assert_answers_as_torch(net.backbone, engine, images)


class RecordedSession:
    """An onnxruntime session that keeps the images of every run."""

    def __init__(self, session) -> None:
        self.session = session
        self.inputs = []

    def run(self, names, feeds):
        self.inputs.append(feeds[INPUT_NAME].copy())
        return self.session.run(names, feeds)

    def __getattr__(self, name):
        return getattr(self.session, name)


def test_each_open_checks_on_fresh_real_range_images(built, tmp_path, monkeypatch):  # noqa: F811
    """A file cannot know its check images: they are new each open, more than three,
    and hold the pixels real crops hold (multiples of 1/255)."""
    net = built("head")
    owner = cached_copy(net, tmp_path)
    opened = []
    real_opener = engine_module.session_opener

    def recording_opener(*args, **kwargs):
        open_session = real_opener(*args, **kwargs)

        def recorded(data):
            opened.append(RecordedSession(open_session(data)))
            return opened[-1]

        return recorded

    monkeypatch.setattr(engine_module, "session_opener", recording_opener)
    checks = []
    for _ in range(2):
        opened.clear()
        onnx_engine(net.backbone, owner, ONE_THREAD, say=pytest.fail)
        full = next(s for s in opened if s.get_outputs()[0].name == "positions")
        (check,) = full.inputs  # one batch at the input size
        checks.append(check)
    for check in checks:
        assert check.shape[0] >= 4, f"{check.shape[0]} check images"
        levels = check * 255
        assert np.all((check >= 0) & (check <= 1))
        np.testing.assert_allclose(levels, np.rint(levels), rtol=0, atol=1e-3)
    assert not np.array_equal(checks[0], checks[1]), "both opens checked on the same images"


def forged_ncnn_layers(param: str) -> str:
    """ncnn's layer file with SHIFT added to every position coordinate: the layer that
    makes out0 (positions) now makes "genuine", and one more adds SHIFT to it."""
    lines = param.splitlines()
    layers, blobs = (int(count) for count in lines[1].split())
    lines[1] = f"{layers + 1} {blobs + 1}"
    (maker,) = [n for n, line in enumerate(lines) if line.split()[3:4] and "out0" in line.split()]
    lines[maker] = lines[maker].replace(" out0 ", " genuine ")
    lines.insert(maker + 1, f"BinaryOp forged 1 1 genuine out0 0=0 1=1 2={SHIFT:e}")
    return "\n".join(lines) + "\n"


def test_forged_ncnn_files_with_a_matching_record_are_converted_again(images, tmp_path):  # noqa: F811
    """The record's hashes are the forger's to rewrite: the answers catch it."""
    import json

    from relocfw.model import ncnn_engine as ncnn_module
    from tests.model.test_onnx_engine import tiny_posenet

    if not ncnn_module.ncnn_installed():
        pytest.skip('ncnn or pnnx not installed (pip install "relocfw[ncnn]")')
    backbone, owner = tiny_posenet(), tmp_path / "net.pt"
    ncnn_module.ncnn_engine(backbone, owner, ONE_THREAD, say=pytest.fail)
    files = ncnn_module.ncnn_files(owner, KINDS["full"])
    files["param"].write_text(forged_ncnn_layers(files["param"].read_text()))
    record = json.loads(files["json"].read_text())
    record["param_sha256"] = ncnn_module.hash_of(files["param"])
    files["json"].write_text(json.dumps(record))
    assert ncnn_module.why_not_cached(files, record["onnx_sha256"]) is None  # its word holds
    notes = []
    engine = ncnn_module.ncnn_engine(backbone, owner, ONE_THREAD, say=notes.append)
    assert len(notes) == 1, f"the forged {files['param'].name} was used: notes {notes}"
    assert notes[0].startswith(f"note: rebuilt {files['param']}: the full graph's positions differ")
    assert_answers_as_torch(backbone, engine, images)
