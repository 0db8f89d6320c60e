"""ONNX export of a backbone: the network a robot runs with onnxruntime, without relocfw.

The graph takes `images` float32 [B, 3, s, s], RGB in [0, 1] (dynamic batch), and
returns `positions` [B, 3] (metres, world frame), `quaternions` [B, 4] (unit, w first)
and `features` [B, D] (the descriptor the map indexes). The input normalisation and
the mapping of normalised positions back to the world frame are inside the graph, as
they are inside every Backbone; what stays outside is the crop (relocfw.imaging.Strip)
and uint8 / 255 (see docs/onnx.md).

Exporter: torch's TorchScript-based exporter (`dynamo=False`). The torch.export-based
one (torch's default since 2.9) needs the `onnxscript` package on top of onnx, and
exporting the same tiny PoseNet took 14 s with it against 0.5 s (torch 2.13, CPU);
the TorchScript one works on every torch this project allows (>= 2.1), and its graph
is checked against torch below on every export. It is deprecated (a DeprecationWarning):
when a torch release drops it, pass `dynamo=True` with
`dynamic_shapes={"images": {0: torch.export.Dim("batch")}}` and add onnxscript to
the `onnx` extra; the names and the dynamic batch of the graph stay the same.
"""

from __future__ import annotations

import copy
import hashlib
import importlib
import io
from pathlib import Path
from types import ModuleType

import numpy as np
import torch
from torch import nn

from relocfw import __version__
from relocfw.checkpoints import atomic_write
from relocfw.errors import ConfigError, DataError
from relocfw.interfaces import Backbone

INPUT_NAME = "images"
OUTPUT_NAMES = ("positions", "quaternions", "features")
# 17: run by onnxruntime since 1.13 (the extra asks for >= 1.16) and by the runtimes
# robots tend to carry (TensorRT >= 8.5, OpenVINO); nothing in these networks needs more.
OPSET = 17
INSTALL_HINT = 'pip install "relocfw[onnx]"'
# Metadata written into the graph (onnxruntime: session.get_modelmeta().custom_metadata_map),
# so a robot reads the input size and the crop geometry from the file itself.
INPUT_SIZE_KEY = "relocfw.input_size"
CROP_SCALE_KEY = "relocfw.crop_scale"
FEATURE_DIM_KEY = "relocfw.feature_dim"
WEIGHTS_KEY = "relocfw.weights_sha256"
VERSION_KEY = "relocfw.version"
# Largest |onnxruntime - torch| accepted on the check batch before writing (relative to
# the value's size above 1): float32 kernels differ in summation order, not more.
TOLERANCE = 1e-3


def require(module: str, purpose: str) -> ModuleType:
    """Import an optional package, or ConfigError saying how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError as error:
        raise ConfigError(f"{purpose} needs the package {module!r}: {INSTALL_HINT}") from error


def onnx_path(model: Path, out: str | None = None) -> Path:
    """Where the ONNX network of model file `model` lies: `out`, or MODEL.onnx beside it."""
    if out:
        return Path(out).expanduser()
    model = Path(model)
    return model.with_name(model.name + ".onnx")


def weights_fingerprint(backbone: Backbone) -> str:
    """SHA-256 of the backbone's state (weights and buffers): ties an ONNX file to the
    model file it was exported from, so a stale export is refused, not used."""
    digest = hashlib.sha256()
    for key, value in sorted(backbone.state_dict().items()):
        tensor = value.detach().cpu().contiguous()
        digest.update(f"{key}:{tensor.dtype}:{tuple(tensor.shape)}".encode())
        digest.update(tensor.numpy().tobytes())
    return digest.hexdigest()


class PoseGraph(nn.Module):
    """The backbone with its PoseOutput as a plain tuple: what the exporter can trace."""

    def __init__(self, backbone: Backbone) -> None:
        super().__init__()
        self.backbone = backbone

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        output = self.backbone(images)
        return output.positions, output.quaternions, output.features


def dropout_free_copy(backbone: Backbone) -> Backbone:
    """A CPU, eval-mode, contiguous-layout copy with Monte Carlo sampling off.

    A copy, so the caller's backbone (on its device, in its layout, with its
    mc_samples) is left as it was.
    """
    network = copy.deepcopy(backbone).cpu().float().eval()
    network.to(memory_format=torch.contiguous_format)
    if "mc_samples" in network.test_time_options:
        network.mc_samples = 0
    return network


def export_onnx(backbone: Backbone, path: Path) -> dict[str, float]:
    """Write `backbone` to `path` as ONNX (atomically), after checking that onnxruntime
    answers as torch does on a batch of random images.

    Returns:
        The largest |onnxruntime - torch| of each output on the check batch.

    Raises:
        ConfigError: onnx or onnxruntime is not installed.
        DataError: onnxruntime's answers differ from torch's (nothing is written).
    """
    onnx = require("onnx", "ONNX export")
    runtime = require("onnxruntime", "ONNX export")
    network = dropout_free_copy(backbone)
    size = int(network.input_size)
    generator = torch.Generator().manual_seed(0)
    traced_with = torch.rand(2, 3, size, size, generator=generator)
    buffer = io.BytesIO()
    with torch.no_grad():
        torch.onnx.export(
            PoseGraph(network),
            (traced_with,),
            buffer,
            dynamo=False,  # see the module docstring
            input_names=[INPUT_NAME],
            output_names=list(OUTPUT_NAMES),
            dynamic_axes={name: {0: "batch"} for name in (INPUT_NAME, *OUTPUT_NAMES)},
            opset_version=OPSET,
            do_constant_folding=True,
        )
    graph = onnx.load_from_string(buffer.getvalue())
    onnx.checker.check_model(graph)
    graph.doc_string = (
        f"relocfw {type(backbone).__name__}: images [B,3,{size},{size}] RGB in [0,1] -> "
        "positions [B,3] (m, world), quaternions [B,4] (w first), features [B,D]"
    )
    onnx.helper.set_model_props(
        graph,
        {
            INPUT_SIZE_KEY: str(size),
            CROP_SCALE_KEY: repr(float(network.crop_scale)),
            FEATURE_DIM_KEY: str(int(network.feature_dim)),
            WEIGHTS_KEY: weights_fingerprint(backbone),
            VERSION_KEY: __version__,
        },
    )
    data = graph.SerializeToString()
    # Three images, not the two traced with: the check also proves the batch is dynamic.
    check = torch.rand(3, 3, size, size, generator=generator)
    session = runtime.InferenceSession(data, providers=["CPUExecutionProvider"])
    answers = session.run(list(OUTPUT_NAMES), {INPUT_NAME: check.numpy()})
    with torch.no_grad():
        expected = [t.numpy() for t in PoseGraph(network)(check)]
    differences = {}
    for name, got, want in zip(OUTPUT_NAMES, answers, expected, strict=True):
        differences[name] = float(np.max(np.abs(got - want)))
        if not np.allclose(got, want, rtol=TOLERANCE, atol=TOLERANCE):
            raise DataError(
                f"{path}: not written: onnxruntime's {name} differ from torch's by up to "
                f"{differences[name]:.3g} on the check images"
            )
    with atomic_write(Path(path), "wb") as stream:
        stream.write(data)
    return differences
