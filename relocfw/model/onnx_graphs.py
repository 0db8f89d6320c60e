"""The inference engine's ONNX graphs of a backbone, exported once and cached
(relocfw.model.onnx_engine.graph_home says where).

`engine=onnx` (relocfw.model.onnx_engine) runs every network pass of a query with
onnxruntime. A query needs up to three parts of the network, each its own graph:

- full: images [B, 3, s, s] -> positions, quaternions, features (the robot's graph,
  relocfw.model.onnx_export): plain scoring, the map, the chosen crop's pose.
- maps: images [B, 3, H, W], any size -> the trunk's last maps before pooling:
  scoring=shared (one pass over the whole strip) and the Monte Carlo variants whose
  first dropout sits on those maps (head, kendall).
- lower: images -> the layers below every dropout (`DropoutBackbone.trunk_lower`),
  for the "all" variant, whose samples rerun everything above them.

What runs once per Monte Carlo sample (a dropout, the descriptor layer, the
regressor) stays in torch: for head and kendall it is under 1% of a pass, and a
graph with the mask as an input would be a second network to keep in step.

Each file holds the weights' fingerprint, its kind and relocfw's graph format in its
metadata; a file that cannot be read, holds other weights, another kind or format,
or answers differently from torch on the check images is rebuilt (atomically), never
used. The metadata is only its writer's word (a file beside a model comes from
wherever the model came from), so the check images are fresh each open and hold the
pixels real crops hold (`check_images`): no file can know them in advance.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from relocfw.core.atomic_files import atomic_write
from relocfw.core.errors import DataError
from relocfw.core.imaging import to_network_input
from relocfw.core.interfaces import Backbone
from relocfw.model.dropout_backbone import DropoutBackbone
from relocfw.model.onnx_export import (
    INPUT_NAME,
    OUTPUT_NAMES,
    WEIGHTS_KEY,
    PoseGraph,
    require,
    trace,
)

KIND_KEY = "relocfw.engine_graph"
FORMAT_KEY = "relocfw.engine_format"
# Raised when what a graph file holds changes meaning; older files are then rebuilt.
GRAPH_FORMAT = "1"
MAPS_OUTPUT = "maps"
# Largest |onnxruntime - torch| a graph may show on the check images, relative to the
# value above 1 (and to the output's size below 1): what the engine promises is
# torch's answer to 1e-4; float32 kernels differ by summation order, about 1e-6.
ENGINE_TOLERANCE = 1e-4
# Check images at the input size each time a graph is opened (`check_images`): noise
# and smooth shading twice each, a batch that costs little (docs/engine.md measures it).
CHECK_IMAGES = 4


class PartGraph(nn.Module):
    """images -> one of the backbone's maps methods (`feature_maps`: the trunk's last
    maps; `lower_maps`: the layers below every dropout), as a module to trace."""

    def __init__(self, backbone: Backbone, method: str) -> None:
        super().__init__()
        self.backbone = backbone
        self.method = method

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return getattr(self.backbone, self.method)(images)


@dataclass(frozen=True)
class GraphKind:
    """One part of the network as a graph: its name, outputs and which axes vary."""

    name: str
    outputs: tuple[str, ...]
    any_size: bool  # height and width dynamic (strips), else the input size only

    def module(self, network: Backbone) -> nn.Module:
        if self.name == "full":
            return PoseGraph(network)
        return PartGraph(network, "feature_maps" if self.name == "maps" else "lower_maps")

    def check_sizes(self, side: int) -> list[tuple[int, int]]:
        """(height, width) of the check images: a landscape and a portrait strip too
        when the graph takes any size, since a size baked into the trace fails there."""
        if not self.any_size:
            return [(side, side)]
        return [(side, side), (side, side + side // 3 + 5), (side + side // 2 + 3, side)]


FULL = GraphKind("full", OUTPUT_NAMES, any_size=False)
MAPS = GraphKind("maps", (MAPS_OUTPUT,), any_size=True)
LOWER = GraphKind("lower", (MAPS_OUTPUT,), any_size=True)
KINDS = {kind.name: kind for kind in (FULL, MAPS, LOWER)}


def kinds_needed(backbone: Backbone) -> list[GraphKind]:
    """The graphs a backbone's queries use: full always; maps when it shares strips or
    samples dropout on its maps; lower for the "all" dropout variant."""
    kinds = [FULL]
    variant = getattr(backbone, "dropout_variant", None)
    if backbone.shares_strip or isinstance(backbone, DropoutBackbone):
        kinds.append(MAPS)
    if isinstance(backbone, DropoutBackbone) and variant == "all":
        kinds.append(LOWER)
    return kinds


def graph_bytes(network: Backbone, kind: GraphKind, fingerprint: str, version: str) -> bytes:
    """The serialised, checked graph of one part of `network` (a dropout-free copy)."""
    onnx = require("onnx", "engine=onnx")
    dynamic = {0: "batch", 2: "height", 3: "width"} if kind.any_size else {0: "batch"}
    axes = {INPUT_NAME: dynamic}
    for name in kind.outputs:  # poses per image; maps as big as the image
        axes[name] = {0: "batch"} if name in OUTPUT_NAMES else dynamic
    # Tracer warnings about shapes read as Python numbers: the check on other sizes
    # (largest_difference) is what proves the graph right at every size.
    data = trace(
        kind.module(network).eval(),
        int(network.input_size),
        kind.outputs,
        axes,
        quiet_tracer=True,
    )
    graph = onnx.load_from_string(data)
    onnx.checker.check_model(graph)
    onnx.helper.set_model_props(
        graph,
        {
            WEIGHTS_KEY: fingerprint,
            KIND_KEY: kind.name,
            FORMAT_KEY: GRAPH_FORMAT,
            "relocfw.version": version,
        },
    )
    return graph.SerializeToString()


def check_images(count: int, height: int, width: int, rng: np.random.Generator) -> torch.Tensor:
    """`count` images [count, 3, height, width] a graph file cannot predict, as the
    pipeline feeds them: uint8 pixels / 255 (relocfw.core.imaging.to_network_input).

    `rng` is fresh per open (seeded by the OS), so no file can hold its check's answers,
    and the pixels are whole levels / 255 as a real crop's are (continuous values are
    something a forged graph could test for). Every other image is smooth random
    shading, not noise. This raises the bar, it proves nothing: noise and smooth
    shading still differ from photographs in their gradients, so a graph built to
    tell them apart could still answer checks honestly and queries falsely.
    """
    pixels = np.empty((count, 3, height, width), dtype=np.uint8)
    for number in range(count):
        if number % 2 == 0:
            pixels[number] = rng.integers(0, 256, (3, height, width), dtype=np.uint8)
        else:
            grid = torch.from_numpy(rng.random((1, 3, *rng.integers(2, 9, 2))))
            shading = nn.functional.interpolate(grid, (height, width), mode="bilinear")
            pixels[number] = np.rint(shading[0].numpy() * 255)
    return to_network_input(torch.from_numpy(pixels))


def checked_answers(
    session: Any, network: Backbone, kind: GraphKind, rng: np.random.Generator | None = None
) -> Iterator[tuple[str, np.ndarray, np.ndarray, tuple[int, int]]]:
    """(output name, the graph's answer, torch's answer, (height, width)) on fresh check
    images (`check_images`): CHECK_IMAGES at the input size (the batch is dynamic), one
    at each other check size. `rng`: None draws a fresh one from the OS."""
    rng = np.random.default_rng() if rng is None else rng
    module = kind.module(network).eval()
    for number, size in enumerate(kind.check_sizes(int(network.input_size))):
        images = check_images(CHECK_IMAGES if number == 0 else 1, *size, rng)
        answers = session.run(list(kind.outputs), {INPUT_NAME: images.numpy()})
        with torch.no_grad():
            expected = module(images)
        expected = expected if isinstance(expected, tuple) else (expected,)
        for name, got, want in zip(kind.outputs, answers, expected, strict=True):
            yield name, np.asarray(got), want.numpy(), size


def largest_difference(session: Any, network: Backbone, kind: GraphKind) -> float:
    """Largest |graph - torch| of the graph's outputs on fresh check images of every
    check size (`checked_answers`); DataError when one is beyond ENGINE_TOLERANCE."""
    largest = 0.0
    for name, got, want, (height, width) in checked_answers(session, network, kind):
        # Absolute tolerance scaled down for outputs far below 1 (an untrained
        # network's maps), so a graph of other weights cannot pass as noise.
        scale = min(1.0, float(np.max(np.abs(want), initial=0.0)))
        atol = ENGINE_TOLERANCE * max(scale, 1e-6)
        if got.shape != want.shape or not np.allclose(got, want, ENGINE_TOLERANCE, atol):
            detail = (
                f"shape {got.shape} against {want.shape}"
                if got.shape != want.shape
                else f"up to {np.max(np.abs(got - want)):.3g}"
            )
            raise DataError(
                f"the {kind.name} graph's {name} differ from torch's ({detail}) on "
                f"{height} x {width} check images"
            )
        largest = max(largest, float(np.max(np.abs(got - want))))
    return largest


def graph_metadata(session: Any) -> dict[str, str]:
    return dict(session.get_modelmeta().custom_metadata_map)


def why_stale(session: Any, kind: GraphKind, fingerprint: str) -> str | None:
    """Why a loaded graph file cannot serve (None: it can)."""
    metadata = graph_metadata(session)
    if metadata.get(FORMAT_KEY) != GRAPH_FORMAT:
        return f"graph format {metadata.get(FORMAT_KEY)!r}, not {GRAPH_FORMAT!r}"
    if metadata.get(KIND_KEY) != kind.name:
        return f"it holds the {metadata.get(KIND_KEY)!r} graph"
    if metadata.get(WEIGHTS_KEY) != fingerprint:
        return "it was exported from other weights"
    return None


def write_graph(data: bytes, path: Path) -> None:
    """All or nothing: a run killed mid-write leaves no half graph to load."""
    with atomic_write(path, "wb") as stream:
        stream.write(data)
