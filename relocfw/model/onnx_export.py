"""ONNX export of a backbone: the network a robot runs with onnxruntime, without relocfw.

The graph takes `images` float32 [B, 3, s, s], RGB in [0, 1] (dynamic batch), and
returns `positions` [B, 3] (metres, world frame), `quaternions` [B, 4] (unit, w first)
and `features` [B, D] (the descriptor the map indexes). The input normalisation and
the mapping of normalised positions back to the world frame are inside the graph, as
they are inside every Backbone; what stays outside is the crop (relocfw.core.imaging.Strip)
and uint8 / 255 (see docs/onnx.md).

Exporter: torch's TorchScript-based exporter (`dynamo=False`). The torch.export-based
one (torch's default since 2.9) needs the `onnxscript` package on top of onnx, and
exporting the same tiny PoseNet took 14 s with it against 0.5 s (torch 2.13, CPU);
the TorchScript one is in every torch this project allows (>= 2.1; before 2.5 it is
the only one, and `export` has no `dynamo` argument), and its graph is checked against
torch on every export. It is deprecated since 2.9 (the warning is silenced below):
when a torch release drops it, pass `dynamo=True` with
`dynamic_shapes={"images": {0: torch.export.Dim("batch")}}` and add onnxscript to
the `onnx` extra; the names and the dynamic batch of the graph stay the same.
"""

from __future__ import annotations

import copy
import hashlib
import importlib
import inspect
import io
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import torch
from torch import nn

from relocfw.core.atomic_files import atomic_write
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.interfaces import Backbone
from relocfw.core.version import VERSION

INPUT_NAME = "images"
OUTPUT_NAMES = ("positions", "quaternions", "features")
# 17: run by onnxruntime since 1.13 (the extra asks for >= 1.16) and by the recent
# TensorRT and OpenVINO releases robots carry; nothing in these networks needs more.
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
# The TorchScript exporter (see the module docstring); torch < 2.5 has only that one.
LEGACY_EXPORTER = (
    {"dynamo": False} if "dynamo" in inspect.signature(torch.onnx.export).parameters else {}
)
QUIET_WARNINGS = (
    "You are using the legacy TorchScript-based ONNX export",
    "The feature will be removed",
    "Constant folding - Only steps=1",
)


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


def export_destination(model: Path, out: str | None = None) -> Path:
    """Where task=export may write the ONNX network of model file `model` (onnx_path).

    An export replaces only an ONNX file: never the model file it comes from (compared
    after resolving both, so `./m` and `m`, or a link to it, are the same file), and
    no other existing file unless its name ends in `.onnx`. The rule is the name, not
    the content: predictable, and a user's file with another suffix is never lost.

    Raises:
        ConfigError: naming export.out, when the destination is not one to write.
    """
    model = Path(model).expanduser()
    target = onnx_path(model, out)
    named = f"export.out={out}" if out else f"export.out (default {target})"
    if target.resolve() == model.resolve() or (
        target.exists() and model.exists() and target.samefile(model)
    ):
        raise ConfigError(
            f"{named} is the model file itself: exporting would replace it with the ONNX "
            f"network; leave export.out unset (writes {onnx_path(model)}) or name another file"
        )
    if target.exists() and not target.is_file():
        raise ConfigError(f"{named} is a folder, not a file: name a file ending in .onnx")
    if target.exists() and target.suffix.lower() != ".onnx":
        raise ConfigError(
            f"{named}: {target} exists and is not an ONNX file (its name does not end in "
            ".onnx); task=export replaces only .onnx files: name another file"
        )
    return target


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
    # eval() on the wrapper too: the exporter restores the wrapper's mode recursively
    # afterwards, and a wrapper left in training mode would switch dropout on below.
    pose_graph = PoseGraph(dropout_free_copy(backbone)).eval()
    graph = onnx.load_from_string(trace(pose_graph, int(pose_graph.backbone.input_size)))
    onnx.checker.check_model(graph)
    network = pose_graph.backbone
    size = int(network.input_size)
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
            VERSION_KEY: VERSION,
        },
    )
    data = graph.SerializeToString()
    session = runtime.InferenceSession(data, providers=["CPUExecutionProvider"])
    differences = compare_with_torch(session, pose_graph, path)
    with atomic_write(Path(path), "wb") as stream:
        stream.write(data)
    return differences


def trace(
    module: nn.Module,
    input_size: int,
    output_names: Sequence[str] = OUTPUT_NAMES,
    dynamic_axes: Mapping[str, Mapping[int, str]] | None = None,
    quiet_tracer: bool = False,
) -> bytes:
    """The serialised ONNX graph of `module` on images [B, 3, s, s], the batch dynamic
    unless `dynamic_axes` (by input / output name) says more.

    `quiet_tracer`: also silence the tracer's warnings about shapes read as Python
    numbers, for a graph whose check at other sizes is what proves it right.
    """
    traced_with = torch.rand(
        2, 3, input_size, input_size, generator=torch.Generator().manual_seed(0)
    )
    if dynamic_axes is None:
        dynamic_axes = {name: {0: "batch"} for name in (INPUT_NAME, *output_names)}
    buffer = io.BytesIO()
    with torch.no_grad(), warnings.catch_warnings():
        # Known and harmless: the exporter's own deprecation (see the module docstring)
        # and EfficientNet's strided slices left unfolded; compare_with_torch is the test.
        for message in QUIET_WARNINGS:
            warnings.filterwarnings("ignore", message=message)
        if quiet_tracer:
            warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        torch.onnx.export(
            module,
            (traced_with,),
            buffer,
            **LEGACY_EXPORTER,
            input_names=[INPUT_NAME],
            output_names=list(output_names),
            dynamic_axes={name: dict(axes) for name, axes in dynamic_axes.items()},
            opset_version=OPSET,
            do_constant_folding=True,
        )
    return buffer.getvalue()


def compare_with_torch(session: Any, pose_graph: PoseGraph, path: Path) -> dict[str, float]:
    """Largest |onnxruntime - torch| per output on random images; DataError naming
    `path` (not written) when one is beyond TOLERANCE."""
    size = int(pose_graph.backbone.input_size)
    # Three images, not the two traced with: the check also proves the batch is dynamic.
    check = torch.rand(3, 3, size, size, generator=torch.Generator().manual_seed(1))
    answers = session.run(list(OUTPUT_NAMES), {INPUT_NAME: check.numpy()})
    with torch.no_grad():
        expected = [t.numpy() for t in pose_graph(check)]
    differences = {}
    for name, got, want in zip(OUTPUT_NAMES, answers, expected, strict=True):
        differences[name] = float(np.max(np.abs(got - want)))
        if not np.allclose(got, want, rtol=TOLERANCE, atol=TOLERANCE):
            raise DataError(
                f"{path}: not written: onnxruntime's {name} differ from torch's by up to "
                f"{differences[name]:.3g} on the check images"
            )
    return differences
