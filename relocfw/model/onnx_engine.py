"""engine=onnx: a trained backbone's graphs, exported once per checkpoint and cached
beside it, opened as an OnnxBackbone (relocfw.model.onnx_backbone).

`onnx_engine(backbone, owner, options)` exports (or reuses) the graphs the backbone's
queries need (relocfw.model.onnx_graphs.kinds_needed) as `OWNER.<kind>.onnx` beside
the checkpoint or model file `owner`, checks every graph against torch on seeded
images each time it is opened, and rebuilds a file that is unreadable, stale or
wrong. When onnxruntime is missing or a graph cannot be made to match torch it raises
EngineUnavailableError with the reason; the CLI then runs torch and says why in one line.

Int8 (`EngineOptions.int8`): onnxruntime's quantisation of the float graphs, written
as `OWNER.<kind>.int8-<mode>.onnx`. "static" calibrates activations on map images
(training data, never queries) and needs them; "dynamic" quantises weights only.
Quantised graphs answer differently from torch by design, so they are checked for
finite answers only; what they cost in accuracy is measured (docs/results/engine.md).
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import Strip, to_network_input
from relocfw.core.interfaces import Backbone
from relocfw.core.version import VERSION
from relocfw.model.onnx_backbone import OnnxBackbone, trained_network
from relocfw.model.onnx_export import (
    INPUT_NAME,
    WEIGHTS_KEY,
    dropout_free_copy,
    weights_fingerprint,
)
from relocfw.model.onnx_graphs import (
    FORMAT_KEY,
    GRAPH_FORMAT,
    KIND_KEY,
    GraphKind,
    graph_bytes,
    graph_metadata,
    kinds_needed,
    largest_difference,
    why_stale,
    write_graph,
)

INT8_MODES = ("none", "dynamic", "static")
INT8_KEY = "relocfw.int8"
RECIPE_KEY = "relocfw.int8_recipe"
# How static graphs are quantised; a cached graph of another recipe is rebuilt. 7-bit
# weights (reduce_range): on CPUs without AVX-512 VNNI (AVX2's u8 x s8 products
# saturate in 16 bits) they halved int8's pose deviation from float32 on Red Kitchen
# training frames (median 3.6 -> 1.8 cm, orientation 1.55 -> 0.77 deg), at the same
# speed; percentile or entropy calibration, 128 images or float first / last layers
# did not do better (docs/engine.md#int8).
INT8_RECIPE = "qdq per-channel s8 reduce_range, u8 activations, minmax, 32 map images"
CALIBRATION_IMAGES = 32  # map images static quantisation calibrates on (evenly spread)


class EngineUnavailableError(Exception):
    """The engine cannot run this backbone; the message says why (torch runs instead)."""


@dataclass(frozen=True)
class EngineOptions:
    """How onnxruntime runs the graphs.

    Args:
        threads: intra-op threads; None: the cores this process may use
            (`available_cores`).
        int8: "none", "dynamic" (weights) or "static" (weights and activations,
            calibrated on map images).
        spinning: let idle onnxruntime threads spin for work. Off by default: between
            passes the pipeline runs torch and BLAS code on the same cores, which
            spinning threads slow down (benchmarks/engine_cost.py measures both).
    """

    threads: int | None = None
    int8: str = "none"
    spinning: bool = False

    def __post_init__(self) -> None:
        if self.int8 not in INT8_MODES:
            choices = ", ".join(INT8_MODES)
            raise ConfigError(f"onnx.int8 must be one of {choices}, got {self.int8!r}")
        if self.threads is not None and int(self.threads) < 1:
            raise ConfigError(f"onnx.threads must be >= 1 (null: every core), got {self.threads}")


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity), capped by OMP_NUM_THREADS
    when that is set, as torch's own thread count is."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        cores = os.cpu_count() or 1
    limit = os.environ.get("OMP_NUM_THREADS", "")
    if limit.isdigit() and int(limit) > 0:
        cores = min(cores, int(limit))
    return max(1, cores)


def graph_path(owner: Path, kind: GraphKind, int8: str = "none") -> Path:
    """Where the graph of `kind` of checkpoint / model file `owner` is cached."""
    suffix = "" if int8 == "none" else f".int8-{int8}"
    owner = Path(owner)
    return owner.with_name(f"{owner.name}.{kind.name}{suffix}.onnx")


def onnx_engine(
    backbone: Backbone,
    owner: Path,
    options: EngineOptions | None = None,
    calibration: Sequence[np.ndarray] | None = None,
    say: Callable[[str], None] = print,
) -> OnnxBackbone:
    """`backbone` run by onnxruntime, its graphs cached beside `owner`.

    Args:
        backbone: the trained torch backbone (or an OnnxBackbone: its source is used).
        owner: the checkpoint or model file the weights come from; graphs are written
            beside it as OWNER.<kind>.onnx.
        calibration: map images (H x W x 3 uint8) for int8="static".
        say: where notes go (a rebuilt graph and why).

    Raises:
        EngineUnavailableError: onnxruntime or onnx is missing, a graph does not match
            torch, or a needed graph cannot be written nor made in memory.
        ConfigError: int8="static" without calibration images and no cached graph.
    """
    options = options or EngineOptions()
    try:
        import onnx  # noqa: F401 - both are needed; say which one is missing
        import onnxruntime
    except ImportError as error:
        raise EngineUnavailableError(
            f'engine=onnx needs {error.name!r} (pip install "relocfw[onnx]")'
        ) from error
    source = trained_network(backbone)
    network = dropout_free_copy(source)
    fingerprint = weights_fingerprint(source)
    threads = int(options.threads or available_cores())
    session_options = onnxruntime.SessionOptions()
    session_options.intra_op_num_threads = threads
    session_options.inter_op_num_threads = 1
    session_options.add_session_config_entry(
        "session.intra_op.allow_spinning", "1" if options.spinning else "0"
    )

    def open_session(data: bytes | str) -> Any:
        cpu = ["CPUExecutionProvider"]
        return onnxruntime.InferenceSession(data, session_options, providers=cpu)

    sessions = {}
    for kind in kinds_needed(source):
        session, data = float_graph(network, kind, owner, fingerprint, open_session, say)
        if options.int8 != "none":
            session = int8_graph(
                network,
                kind,
                owner,
                fingerprint,
                options.int8,
                data,
                calibration,
                open_session,
                say,
            )
        sessions[kind.name] = session
    precision = "float32" if options.int8 == "none" else f"int8 {options.int8}"
    description = f"onnxruntime {onnxruntime.__version__}, {precision}, {threads} threads"
    return OnnxBackbone(source, sessions, description)


def float_graph(
    network: Backbone,
    kind: GraphKind,
    owner: Path,
    fingerprint: str,
    open_session: Callable[[bytes | str], Any],
    say: Callable[[str], None],
) -> tuple[Any, bytes]:
    """The checked float graph of `kind`: the cached file, or a fresh export written
    over it. Returns the session and the graph's bytes (int8 starts from them)."""
    path = graph_path(owner, kind)
    if path.is_file():
        try:
            data = path.read_bytes()
            session = open_session(data)
            stale = why_stale(session, kind, fingerprint)
            if stale is None:
                largest_difference(session, network, kind)
                return session, data
            say(f"note: rebuilding {path}: {stale}")
        except DataError as error:
            say(f"note: rebuilding {path}: {error}")
        except Exception as error:  # onnxruntime's own types for an unreadable file
            say(f"note: rebuilding {path}: cannot be read ({type(error).__name__})")
    try:
        data = graph_bytes(network, kind, fingerprint, VERSION)
        session = open_session(data)
        largest_difference(session, network, kind)
    except DataError as error:
        raise EngineUnavailableError(str(error)) from error
    except Exception as error:  # the exporter's and onnxruntime's many types
        raise EngineUnavailableError(
            f"the {kind.name} graph cannot be exported ({type(error).__name__}: {error})"
        ) from error
    try:
        write_graph(data, path)
    except OSError as error:
        say(f"note: cannot cache {path} ({error.strerror}); the graph is kept in memory")
    return session, data


def int8_graph(
    network: Backbone,
    kind: GraphKind,
    owner: Path,
    fingerprint: str,
    mode: str,
    float_data: bytes,
    calibration: Sequence[np.ndarray] | None,
    open_session: Callable[[bytes | str], Any],
    say: Callable[[str], None],
) -> Any:
    """The int8 graph of `kind`: cached when its metadata matches, else quantised."""
    path = graph_path(owner, kind, mode)
    if path.is_file():
        try:
            session = open_session(path.read_bytes())
            metadata = graph_metadata(session)
            stale = why_stale(session, kind, fingerprint)
            if stale is None and metadata.get(INT8_KEY) != mode:
                stale = f"it is int8 {metadata.get(INT8_KEY)!r}"
            if stale is None and mode == "static" and metadata.get(RECIPE_KEY) != INT8_RECIPE:
                stale = "it was quantised with another recipe"
            if stale is None:
                check_finite(session, network, kind)
                return session
            say(f"note: rebuilding {path}: {stale}")
        except DataError as error:
            say(f"note: rebuilding {path}: {error}")
        except Exception as error:
            say(f"note: rebuilding {path}: cannot be read ({type(error).__name__})")
    if mode == "static" and not calibration:
        raise ConfigError(
            f"onnx.int8=static calibrates on map images and none are at hand here ({path} "
            "is not cached): build it with task=relocalize or task=compare, or use "
            "onnx.int8=dynamic"
        )
    try:
        data = quantised(float_data, kind, mode, network, calibration, fingerprint)
        session = open_session(data)
        check_finite(session, network, kind)
    except DataError as error:
        raise EngineUnavailableError(str(error)) from error
    except Exception as error:
        raise EngineUnavailableError(
            f"int8 {mode} quantisation of the {kind.name} graph failed "
            f"({type(error).__name__}: {error})"
        ) from error
    try:
        write_graph(data, path)
    except OSError as error:
        say(f"note: cannot cache {path} ({error.strerror}); the graph is kept in memory")
    return session


def quantised(
    float_data: bytes,
    kind: GraphKind,
    mode: str,
    network: Backbone,
    calibration: Sequence[np.ndarray] | None,
    fingerprint: str,
) -> bytes:
    """onnxruntime's int8 quantisation of a float graph, with relocfw's metadata."""
    import onnx
    from onnxruntime import quantization

    with tempfile.TemporaryDirectory(prefix="relocfw-int8-") as folder, quiet_logging():
        source, prepared, target = (Path(folder) / n for n in ("f.onnx", "p.onnx", "q.onnx"))
        source.write_bytes(float_data)
        # Shape inference and graph clean-up first, as onnxruntime's docs advise.
        quantization.shape_inference.quant_pre_process(str(source), str(prepared))
        if mode == "dynamic":
            quantization.quantize_dynamic(
                str(prepared), str(target), weight_type=quantization.QuantType.QInt8
            )
        else:
            reader = CalibrationImages(calibration or [], network)
            quantization.quantize_static(
                str(prepared),
                str(target),
                reader,
                quant_format=quantization.QuantFormat.QDQ,
                per_channel=True,
                reduce_range=True,
                weight_type=quantization.QuantType.QInt8,
                activation_type=quantization.QuantType.QUInt8,
                calibrate_method=quantization.CalibrationMethod.MinMax,
            )
        graph = onnx.load(str(target))
    onnx.helper.set_model_props(
        graph,
        {
            WEIGHTS_KEY: fingerprint,
            KIND_KEY: kind.name,
            FORMAT_KEY: GRAPH_FORMAT,
            INT8_KEY: mode,
            RECIPE_KEY: INT8_RECIPE if mode == "static" else "",
            "relocfw.version": VERSION,
        },
    )
    return graph.SerializeToString()


@contextmanager
def quiet_logging() -> Iterator[None]:
    """onnxruntime's quantisation logs every rescaled weight at INFO on the root
    logger, which Hydra prints: hundreds of lines per graph. Warnings still show."""
    previous = logging.root.manager.disable
    logging.disable(logging.INFO)
    try:
        yield
    finally:
        logging.disable(previous)


class CalibrationImages:
    """onnxruntime's CalibrationDataReader over map images' centre crops, as the
    network sees them (the same Strip and scaling as the pipeline), one at a time."""

    def __init__(self, images: Sequence[np.ndarray], network: Backbone) -> None:
        chosen = np.linspace(0, len(images) - 1, min(CALIBRATION_IMAGES, len(images)))
        self.inputs = []
        for position in np.unique(chosen.round().astype(int)):
            strip = Strip(images[position], network.input_size, float(network.crop_scale))
            window = strip.cut(strip.window(strip.centre_crop()))
            self.inputs.append(to_network_input(window[None]).numpy().astype(np.float32))
        self.position = 0

    def get_next(self) -> dict[str, np.ndarray] | None:
        if self.position >= len(self.inputs):
            return None
        self.position += 1
        return {INPUT_NAME: self.inputs[self.position - 1]}

    def rewind(self) -> None:
        self.position = 0


def check_finite(session: Any, network: Backbone, kind: GraphKind) -> None:
    """DataError unless an int8 graph answers finite values on seeded images."""
    side = int(network.input_size)
    images = torch.rand(2, 3, side, side, generator=torch.Generator().manual_seed(0)).numpy()
    names = [output.name for output in session.get_outputs()]
    for name, answer in zip(names, session.run(None, {INPUT_NAME: images}), strict=True):
        if not np.all(np.isfinite(answer)):
            raise DataError(f"the int8 {kind.name} graph's {name} are not finite")
