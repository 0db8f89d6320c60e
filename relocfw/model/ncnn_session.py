"""NcnnSession: an ncnn network behind onnxruntime's session call (engine=ncnn).

This file imports ncnn, numpy and the standard library only, never relocfw nor torch,
because it is also the probe: `python -P ncnn_session.py PARAM BIN OUTPUTS THREADS
H,W [H,W ...]` loads a network as engine=ncnn does and runs one seeded image of each
size through it. ncnn is C++: a graph it mishandles crashes the process (it did,
before the input was copied), which no exception handler catches. relocfw runs every
network in the probe first (relocfw.model.ncnn_engine), so such a crash ends that
process only and is reported as an error. Run as a script it starts in a tenth of a
second, against two for anything that imports torch.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

# pnnx names the graph's input and outputs in0, out0, out1, ... in the ONNX order.
NCNN_INPUT = "in0"
# ncnn's reduced-precision storage and arithmetic and its GPU path, all off: the
# answers must be torch's float32 ones, on the CPU.
OFF = (
    "use_fp16_packed",
    "use_fp16_storage",
    "use_fp16_arithmetic",
    "use_bf16_packed",
    "use_bf16_storage",
    "use_int8_inference",
    "use_vulkan_compute",
)


class NcnnLoadError(Exception):
    """ncnn cannot load the files, or they are not a converted relocfw graph."""


class NcnnComputeError(Exception):
    """ncnn could not compute an output of a loaded network."""


class NcnnSession:
    """An ncnn network behind onnxruntime's session call, `run(names, feeds)`, so
    OnnxBackbone and the torch check run it as they run a graph.

    Args:
        param, weights: ncnn's layer and weight files (pnnx's naming: in0, out0, ...).
        outputs: the graph's output names, in pnnx's order.
        threads: cores each image's pass runs on.
    """

    def __init__(
        self, param: str | Path, weights: str | Path, outputs: Sequence[str], threads: int
    ) -> None:
        import ncnn

        self.ncnn = ncnn
        # The net first, then its pools: attributes are released in this order, and
        # the net must let go of its blobs before the pools that hold them go.
        self.net = ncnn.Net()
        # Each pass's blobs and scratch memory come from pools kept for the session
        # instead of fresh allocations, as ncnn advises for repeated runs (what they
        # changed in the benchmarks: docs/engine.md#ncnn). ncnn keeps only a pointer
        # to them: the session holds them.
        self.pools = (ncnn.PoolAllocator(), ncnn.PoolAllocator())
        options = self.net.opt
        options.num_threads = int(threads)
        options.blob_allocator, options.workspace_allocator = self.pools
        for name in OFF:
            setattr(options, name, False)
        self.outputs = tuple(outputs)
        self.blobs = tuple(f"out{number}" for number in range(len(self.outputs)))
        # Both return codes are checked: ncnn says why on stderr, not to the caller.
        if self.net.load_param(str(param)) != 0:
            raise NcnnLoadError("ncnn cannot read its layers (.param)")
        if self.net.load_model(str(weights)) != 0:
            raise NcnnLoadError("ncnn cannot read its weights (.bin) for those layers")
        names = (sorted(self.net.input_names()), sorted(self.net.output_names()))
        if names != ([NCNN_INPUT], sorted(self.blobs)):
            raise NcnnLoadError(f"its inputs and outputs are {names}, not in0 and out0..")

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
                        raise NcnnComputeError(f"ncnn could not compute {self.outputs[number]}")
                    answers[number].append(np.array(answer))
        by_name = {name: np.stack(a) for name, a in zip(self.outputs, answers, strict=True)}
        return [by_name[name] for name in (self.outputs if names is None else names)]


def probe(arguments: Sequence[str]) -> int:
    """The probe run (see the module's docstring): 0 when every size ran and gave
    finite answers; else 1 with one line on stderr saying why."""
    param, weights, outputs, threads, *sizes = arguments
    names = [f"out{number}" for number in range(int(outputs))]
    try:
        session = NcnnSession(param, weights, names, int(threads))
        generator = np.random.default_rng(0)
        for size in sizes:
            height, width = (int(side) for side in size.split(","))
            image = generator.random((1, 3, height, width), dtype=np.float32)
            answers = session.run(None, {"images": image})
            if not all(np.all(np.isfinite(answer)) for answer in answers):
                raise NcnnComputeError(f"its answers are not finite at {height} x {width}")
    except (NcnnLoadError, NcnnComputeError) as error:
        print(error, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(probe(sys.argv[1:]))
