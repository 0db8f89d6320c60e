"""OnnxBackbone: the exported network (relocfw.model.onnx_export) run by onnxruntime.

It stands in for the torch backbone it was exported from, inside the same pipeline:
the map, the crop search and the settings still come from the model file, so
`task=localize backend=onnx` answers as `backend=torch` does (to float32 rounding)
and shows what a robot running the ONNX file alone would get.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.interfaces import Backbone
from relocfw.core.pipeline import Relocalizer
from relocfw.core.sampling import configured_samples
from relocfw.core.values import PoseOutput
from relocfw.model.onnx_export import (
    INPUT_NAME,
    OUTPUT_NAMES,
    WEIGHTS_KEY,
    require,
    weights_fingerprint,
)


class OnnxBackbone(Backbone):
    """An onnxruntime session in place of a torch backbone.

    Args:
        path: the ONNX file written by `export_onnx` from `like`.
        like: the torch backbone it was exported from: its input size, descriptor
            length, training crop_scale and position buffers are taken from it (the
            pipeline reads them; the graph itself already answers in metres).
        threads: onnxruntime's intra-op threads; None: torch's thread count, so both
            backends run on the same cores (OMP_NUM_THREADS applies to both).
        providers: onnxruntime execution providers, in order of preference.

    No Monte Carlo sampling (the graph is the dropout-free network) and no
    scoring=shared (the graph has no feature_maps): the pipeline's own checks refuse
    the latter, `onnx_relocalizer` both.
    """

    # Inputs cross to numpy as they are: NCHW contiguous is what the graph expects.
    channels_last = False

    def __init__(
        self,
        path: Path,
        like: Backbone,
        threads: int | None = None,
        providers: Sequence[str] = ("CPUExecutionProvider",),
    ) -> None:
        super().__init__()
        runtime = require("onnxruntime", "backend=onnx")
        path = Path(path)
        if not path.is_file():
            raise DataError(f"ONNX network not found: {path} (write it with relocfw task=export)")
        options = runtime.SessionOptions()
        options.intra_op_num_threads = int(threads or torch.get_num_threads())
        options.inter_op_num_threads = 1
        try:
            self.session = runtime.InferenceSession(str(path), options, providers=list(providers))
        except Exception as error:  # onnxruntime raises its own types for a bad file
            raise DataError(f"cannot load the ONNX network {path}: {error}") from error
        self.input_size = int(like.input_size)
        self.feature_dim = int(like.feature_dim)
        self.pretrained = bool(like.pretrained)
        self.check_graph(path, like)
        with torch.no_grad():
            self.position_mean.copy_(like.position_mean.detach().cpu())
            self.position_scale.copy_(like.position_scale.detach().cpu())
            self.crop_scale.copy_(like.crop_scale.detach().cpu())

    def check_graph(self, path: Path, like: Backbone) -> None:
        """DataError unless the graph has relocfw's interface and `like`'s weights."""
        inputs = [(i.name, list(i.shape)) for i in self.session.get_inputs()]
        outputs = [o.name for o in self.session.get_outputs()]
        size = self.input_size
        if [(name, shape[1:]) for name, shape in inputs] != [(INPUT_NAME, [3, size, size])]:
            raise DataError(
                f"{path}: expected one input {INPUT_NAME!r} [B, 3, {size}, {size}], got {inputs}"
            )
        if outputs != list(OUTPUT_NAMES):
            raise DataError(f"{path}: expected outputs {list(OUTPUT_NAMES)}, got {outputs}")
        exported_from = self.session.get_modelmeta().custom_metadata_map.get(WEIGHTS_KEY)
        if exported_from != weights_fingerprint(like):
            raise DataError(
                f"{path} holds other weights than the model it should replace (exported "
                "from an earlier model file?): run relocfw task=export model=MODEL again"
            )

    def forward(self, images: torch.Tensor) -> PoseOutput:
        array = np.ascontiguousarray(images.detach().cpu().numpy(), dtype=np.float32)
        answers = self.session.run(list(OUTPUT_NAMES), {INPUT_NAME: array})
        positions, quaternions, features = (torch.from_numpy(a).to(images.device) for a in answers)
        return PoseOutput(positions, quaternions, features)


def onnx_relocalizer(
    relocalizer: Relocalizer, path: Path, threads: int | None = None
) -> Relocalizer:
    """`relocalizer` with its torch backbone replaced by the ONNX network at `path`.

    The map, crop search and every setting are kept.

    Raises:
        ConfigError: the relocalizer scores with scoring=shared or samples Monte Carlo
            dropout, which the ONNX graph cannot do.
        DataError: the file is missing, unreadable or exported from other weights.
    """
    check_onnx_scoring(relocalizer.options.scoring)
    samples = configured_samples(relocalizer.backbone)
    if samples > 0:
        raise ConfigError(
            f"backend=onnx runs the dropout-free network, but the model samples "
            f"backbone.mc_samples={samples} Monte Carlo dropout masks (use backend=torch)"
        )
    return relocalizer.with_backbone(OnnxBackbone(path, relocalizer.backbone, threads))


def check_onnx_scoring(scoring: str) -> None:
    """ConfigError for scoring=shared, which needs the trunk's maps the graph lacks."""
    if scoring == "shared":
        raise ConfigError(
            "backend=onnx cannot use scoring=shared: the ONNX graph returns poses and "
            "descriptors, not the trunk's feature maps (use scoring=plain or backend=torch)"
        )
