"""NcnnSession: an ncnn network behind onnxruntime's session call (engine=ncnn).

Imports ncnn and numpy only, not relocfw's other modules nor torch, so that
relocfw.model.ncnn_probe can run a converted network in a process of its own that
starts in a tenth of a second.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

# pnnx names the graph's input and outputs in0, out0, out1, ... in the ONNX order.
NCNN_INPUT = "in0"
# ncnn's reduced-precision storage and arithmetic, all off: the answers must be torch's.
REDUCED_PRECISION = (
    "use_fp16_packed",
    "use_fp16_storage",
    "use_fp16_arithmetic",
    "use_bf16_packed",
    "use_bf16_storage",
    "use_int8_inference",
)


class NcnnLoadError(Exception):
    """ncnn cannot load the files, or they are not a converted relocfw graph."""


class NcnnSession:
    """An ncnn network behind onnxruntime's session call, `run(names, feeds)`, so
    OnnxBackbone and the torch check run it as they run a graph.

    Args:
        param, weights: ncnn's layer and weight files (pnnx's naming: in0, out0, ...).
        outputs: the graph's output names, in pnnx's order.
        threads: cores each image's pass runs on.
    """

    def __init__(self, param: Path, weights: Path, outputs: Sequence[str], threads: int) -> None:
        import ncnn

        self.ncnn = ncnn
        self.net = ncnn.Net()
        self.net.opt.num_threads = int(threads)
        # Each pass's blobs and scratch memory come from pools kept for the session
        # instead of fresh allocations, as ncnn advises for repeated runs. Held here:
        # ncnn keeps only a pointer (the options would outlive a temporary).
        self.pools = (ncnn.PoolAllocator(), ncnn.PoolAllocator())
        self.net.opt.blob_allocator, self.net.opt.workspace_allocator = self.pools
        for option in REDUCED_PRECISION:
            if hasattr(self.net.opt, option):  # older ncnn lacks some
                setattr(self.net.opt, option, False)
        self.outputs = tuple(outputs)
        self.blobs = tuple(f"out{number}" for number in range(len(self.outputs)))
        # Kept: ncnn reads the weights file when loading, but a failed load says nothing.
        if self.net.load_param(str(param)) != 0 or self.net.load_model(str(weights)) != 0:
            raise NcnnLoadError(f"ncnn cannot load {param} and {Path(weights).name}")
        names = (sorted(self.net.input_names()), sorted(self.net.output_names()))
        if names != ([NCNN_INPUT], sorted(self.blobs)):
            raise NcnnLoadError(f"{param} has inputs and outputs {names}, not in0 and out0..")

    def run(self, names: Sequence[str] | None, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        """The outputs `names` (None: all, as onnxruntime) of the images in `feeds`."""
        (images,) = feeds.values()  # the graphs' one input
        images = np.ascontiguousarray(images, dtype=np.float32)
        if len(images) == 0:  # no shapes to give an empty answer (the pipeline never asks)
            raise ValueError("NcnnSession.run needs at least one image")
        answers: list[list[np.ndarray]] = [[] for _ in self.blobs]
        for image in images:
            with self.net.create_extractor() as extractor:
                # A copy: a Mat over numpy's memory crashes ncnn when the first layer
                # works in place (EfficientNet-Lite0's input scaling does).
                extractor.input(NCNN_INPUT, self.ncnn.Mat(image).clone())
                for number, blob in enumerate(self.blobs):
                    code, answer = extractor.extract(blob)
                    if code != 0:
                        raise RuntimeError(f"ncnn could not compute {self.outputs[number]}")
                    answers[number].append(np.array(answer))
        by_name = {name: np.stack(a) for name, a in zip(self.outputs, answers, strict=True)}
        return [by_name[name] for name in (self.outputs if names is None else names)]
