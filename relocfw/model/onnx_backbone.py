"""OnnxBackbone: a trained torch backbone whose passes onnxruntime runs (engine=onnx),
or ncnn through sessions of the same call (engine=ncnn, relocfw.model.ncnn_session).

It stands in for its torch `source` inside the same pipeline (relocfw.core.scorer):
every dropout-free pass (plain scoring, the map, the chosen crop, random crops) runs
the full graph; scoring=shared runs the maps graph over the whole strip;
scoring=scout runs the `scout` session (the int8 full graph) on the candidates; Monte Carlo
dropout runs the dropout-free layers below the first dropout as a graph and the
sampled layers above it in torch (relocfw.model.onnx_graphs says why). The answers
are the source's to float32 rounding; the source itself is the model (what model
files store, see `trained_network`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from relocfw.core.interfaces import Backbone
from relocfw.core.sampling import configured_samples, sample_share
from relocfw.core.values import PoseOutput
from relocfw.model.dropout_backbone import DropoutBackbone
from relocfw.model.onnx_export import INPUT_NAME, OUTPUT_NAMES
from relocfw.model.onnx_graphs import MAPS_OUTPUT


class OnnxBackbone(Backbone):
    """The torch backbone `source` with its passes run by onnxruntime (or ncnn) sessions.

    Args:
        source: the trained torch backbone (the weights the graphs were exported from).
        sessions: onnxruntime sessions (or relocfw.model.ncnn_session's) by graph
            kind: "full" (required), "maps", "lower" (relocfw.model.onnx_graphs). A
            missing kind's passes run in torch.
        description: how the engine runs, for reports (e.g. "onnxruntime, 2 threads").
        int8: the graphs' quantisation (relocfw.model.onnx_engine.INT8_MODES).
        scout: a session of a cheaper copy of the full graph (the int8 one) for
            scoring=scout's candidates, `sessions` then being float32; None: the full
            graph scouts (what scoring=plain computes).
    """

    # Inputs cross to numpy as they are: NCHW contiguous is what the graphs expect.
    channels_last = False

    def __init__(
        self,
        source: Backbone,
        sessions: Mapping[str, Any],
        description: str,
        int8: str = "none",
        scout: Any = None,
    ) -> None:
        super().__init__()
        if "full" not in sessions:
            raise ValueError("OnnxBackbone needs the full graph's session")
        self.source = source.cpu().eval()
        self.sessions = dict(sessions)
        self.description = description
        self.int8 = int8
        self.scout = scout
        self.input_size = int(source.input_size)
        self.feature_dim = int(source.feature_dim)
        self.pretrained = bool(source.pretrained)
        self.test_time_options = tuple(source.test_time_options)
        self._sample_share: float | None = None
        with torch.no_grad():
            self.position_mean.copy_(source.position_mean.detach().cpu())
            self.position_scale.copy_(source.position_scale.detach().cpu())
            self.crop_scale.copy_(source.crop_scale.detach().cpu())

    # The source's test-time options are this backbone's: relocfw.core.sampling sets
    # mc_samples for the chosen crop's samples and reads it back.
    @property
    def mc_samples(self) -> int:
        return int(getattr(self.source, "mc_samples", 0))

    @mc_samples.setter
    def mc_samples(self, samples: int) -> None:
        self.source.mc_samples = samples

    @property
    def shares_strip(self) -> bool:
        return self.source.shares_strip

    @property
    def sample_share(self) -> float:  # type: ignore[override]
        """The source's share (measured on its torch layers: the graphs hide them)."""
        if self._sample_share is None:
            self._sample_share = sample_share(self.source, torch.device("cpu"))
        return self._sample_share

    def run(self, kind: str, images: torch.Tensor) -> list[np.ndarray]:
        array = graph_input(images)
        session = self.sessions[kind]
        names = list(OUTPUT_NAMES) if kind == "full" else [MAPS_OUTPUT]
        if self.int8 != "dynamic" or len(array) == 1:
            return session.run(names, {INPUT_NAME: array})
        # Dynamic quantisation scales each pass's activations by the whole batch's
        # range: one image per pass keeps an image's answer its own, whatever the
        # windows (or other queries) beside it.
        parts = [session.run(names, {INPUT_NAME: array[i : i + 1]}) for i in range(len(array))]
        return [np.concatenate(outputs) for outputs in zip(*parts, strict=True)]

    def forward(self, images: torch.Tensor) -> PoseOutput:
        if configured_samples(self.source) > 0:
            return self.sampled(images)
        positions, quaternions, features = (torch.from_numpy(a) for a in self.run("full", images))
        return PoseOutput(positions, quaternions, features)

    def sampled(self, images: torch.Tensor) -> PoseOutput:
        """Monte Carlo dropout: the dropout-free layers below the first dropout by the
        graphs, the sampled ones by the source in torch."""
        if not isinstance(self.source, DropoutBackbone):
            return self.source(images)  # a plugin's own sampling: torch throughout
        lower = self.lower_maps if "lower" in self.sessions else None
        return self.source.monte_carlo_answer(images, self.feature_maps, lower)

    def scout_refusal(self) -> str | None:
        if self.scout is None and self.int8 != "none":
            return (
                f"the engine's graphs are int8 {self.int8} throughout, so the chosen crop "
                "would be answered in int8 too: make it with EngineOptions(int8=..., "
                "scout=True), whose other graphs stay float32"
            )
        return None

    def scout_features(self, images: torch.Tensor) -> torch.Tensor:
        if self.scout is None:
            return super().scout_features(images)
        (features,) = self.scout.run(["features"], {INPUT_NAME: graph_input(images)})
        return torch.from_numpy(features)

    def feature_maps(self, images: torch.Tensor) -> torch.Tensor:
        if "maps" not in self.sessions:
            return self.source.feature_maps(images)
        return torch.from_numpy(self.run("maps", images)[0])

    def lower_maps(self, images: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(self.run("lower", images)[0])

    def describe_pooled(self, pooled: torch.Tensor) -> torch.Tensor:
        # One linear layer per candidate: torch, on the source's weights.
        return self.source.describe_pooled(pooled)


def graph_input(images: torch.Tensor) -> np.ndarray:
    """What the graphs take: float32 NCHW, contiguous, on the CPU."""
    return np.ascontiguousarray(images.detach().cpu().numpy(), dtype=np.float32)


def trained_network(backbone: Backbone) -> Backbone:
    """The torch backbone behind `backbone`: what a model file stores and what trains."""
    return backbone.source if isinstance(backbone, OnnxBackbone) else backbone
