"""engine=onnx: a trained backbone's graphs, exported once per checkpoint or model file
and cached, opened as an OnnxBackbone (relocfw.model.onnx_backbone).

`onnx_engine(backbone, owner, options)` exports (or reuses) the graphs the backbone's
queries need (relocfw.model.onnx_graphs.kinds_needed) as `OWNER-<kind>.onnx` beside
the checkpoint or model file `owner`, checks every graph against torch on fresh
random images each time it is opened (a file beside a model comes from wherever the
model came from: its metadata is its writer's word, its answers are checked), and
rebuilds a float graph that is unreadable, stale or wrong. When onnxruntime is
missing or a graph cannot be made to match torch it raises EngineUnavailableError
with the reason; the CLI then runs torch and says why in one line. The CLI names
the owner by `graph_home`: a checkpoint (in the cache) itself, a model file by its
content under cache_dir/graphs/, so no graph is ever written beside a model file.

Int8 (`EngineOptions.int8`): onnxruntime's quantisation of the float graphs, written
as `OWNER-<kind>.int8-<mode>.onnx`, tied to the float graph they were made from.
"static" calibrates activations on map images (training data, never queries) and
needs them, with 7-bit weights that give the same answers on every x86 CPU;
"static_8bit" is the same with 8-bit weights, only on CPUs with VNNI (on AVX2 alone
onnxruntime's u8 x s8 products saturate with them); "dynamic" quantises weights only.
Quantised graphs answer differently from torch by design, so they are held to
INT8_TOLERANCE of torch's float32 answers; a cached one beyond it is refused, not
remade (it was tampered with or damaged; a static one needs map images to remake).
What int8 costs in accuracy is measured (docs/engine.md).
With `EngineOptions.scout` (query.scoring=scout) only the full graph is quantised,
and only to scout the crop search's candidates: every other pass, the chosen crop's
answer included, runs the float32 graphs.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import Strip, to_network_input
from relocfw.core.interfaces import Backbone
from relocfw.core.version import VERSION
from relocfw.model import cpu_flags
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
    KINDS,
    MAPS_OUTPUT,
    GraphKind,
    checked_answers,
    graph_bytes,
    graph_metadata,
    kinds_needed,
    largest_difference,
    why_stale,
    write_graph,
)

INT8_MODES = ("none", "dynamic", "static", "static_8bit")
STATIC_MODES = ("static", "static_8bit")  # calibrated on map images
GRAPHS_FOLDER = "graphs"  # cache_dir/graphs/<model digest>/: a model file's graphs
INT8_KEY = "relocfw.int8"
RECIPE_KEY = "relocfw.int8_recipe"
# How static graphs are quantised; a cached graph of another recipe is rebuilt. 7-bit
# weights (reduce_range): on CPUs without AVX-512 VNNI (AVX2's u8 x s8 products
# saturate in 16 bits) they halved int8's pose deviation from float32 on Red Kitchen
# training frames (median 3.6 -> 1.8 cm, orientation 1.55 -> 0.77 deg); percentile
# calibration, 128 images or float first / last layers gave 1.7-1.8 cm on top of it,
# within the noise (docs/engine.md#int8). static_8bit: the full 8 bits, exact only
# where the CPU multiplies u8 x s8 without saturating (VNNI, see relocfw.model.cpu_flags).
INT8_RECIPES = {
    "static": "qdq per-channel s8 reduce_range, u8 activations, minmax, 32 map images",
    "static_8bit": "qdq per-channel s8, u8 activations, minmax, 32 map images",
    "dynamic": "dynamic s8 weights",
}
FLOAT_KEY = "relocfw.float_graph_sha256"  # the float graph an int8 one was made from
CALIBRATION_IMAGES = 32  # map images static quantisation calibrates on (evenly spread)
# How far a genuine int8 graph's answers may lie from torch's float32 ones on the check
# images (onnx_graphs.check_images), in INT8_UNITS. Measured, the largest of every
# static, static_8bit (saturating on AVX2) and dynamic graph of a tiny PoseNet
# (64 px, 2 weight seeds, calibrated on noise or Red Kitchen frames; 30 opens) and of a
# GoogLeNet at 96 and 224 px (untrained, He-initialised so answers vary by image; 8
# opens), on check images and on Red Kitchen centre crops: positions 0.074 x the
# position scale (GoogLeNet 0.041), quaternions 4.4 deg (1.2), descriptors 0.38 of
# their length (0.12), maps 0.35 (0.09). The CLI tests' model (32 px, three training
# steps, its quaternions barely trained) deviates far more in orientation: up to 27 deg
# over 40 opens on an AVX-512 VNNI CPU and 35 deg on CI's
# (benchmarks/int8_deviation.py), against at least 141 deg for a graph of another
# seed's weights. So the orientation bound is 90 deg, between the two; positions 0.5,
# 7x the largest genuine deviation; descriptors and maps an error as long as torch's
# answer itself (a graph no closer than zeros). The forgery, +100 m, is 40 x
# the tests' position scale.
INT8_TOLERANCE = {"positions": 0.5, "quaternions": 90.0, "features": 1.0, MAPS_OUTPUT: 1.0}
INT8_UNITS = {
    "positions": "x the position scale",
    "quaternions": "deg",
    "features": "of their length",
    MAPS_OUTPUT: "of their length",
}


class EngineUnavailableError(Exception):
    """The engine cannot run this backbone; the message says why (torch runs instead)."""


@dataclass(frozen=True)
class EngineOptions:
    """How onnxruntime (and, for `threads`, ncnn) runs the graphs.

    Args:
        threads: intra-op threads (ncnn's threads with engine=ncnn); None: the cores
            this process may use (`available_cores`).
        int8: "none", "dynamic" (weights), "static" (weights and activations,
            calibrated on map images; 7-bit weights) or "static_8bit" (the same with
            8-bit weights; CPUs with VNNI only).
        spinning: let idle onnxruntime threads spin for work. Off by default: between
            passes the pipeline runs torch and BLAS code on the same cores, which
            spinning threads slow down (benchmarks/engine_cost.py measures both).
        scout: the int8 full graph only scouts candidate crops (query.scoring=scout);
            every other pass runs float32. Needs a static int8 mode: dynamic
            quantisation scales each batch by its own range, so a window's score would
            depend on the candidates beside it.
    """

    threads: int | None = None
    int8: str = "none"
    spinning: bool = False
    scout: bool = False

    def __post_init__(self) -> None:
        if self.int8 not in INT8_MODES:
            choices = ", ".join(INT8_MODES)
            raise ConfigError(f"onnx.int8 must be one of {choices}, got {self.int8!r}")
        if self.scout and self.int8 not in STATIC_MODES:
            given = "" if self.int8 == "none" else f", not onnx.int8={self.int8}"
            raise ConfigError(
                "query.scoring=scout scores candidate crops with the static int8 graph, "
                "whose scores do not depend on the windows beside them: set "
                f"onnx.int8=static (or static_8bit){given}, or use query.scoring=plain"
            )
        if self.threads is not None and int(self.threads) < 1:
            raise ConfigError(f"onnx.threads must be >= 1 (null: every core), got {self.threads}")


def available_cores() -> int:
    """The cores this process may use: its CPU affinity, capped by a container's CPU
    quota (cgroup v2 cpu.max, e.g. docker --cpus=2) and by OMP_NUM_THREADS when set,
    as torch's own thread count is."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        cores = os.cpu_count() or 1
    quota = cgroup_cpu_quota()
    if quota is not None:
        cores = min(cores, quota)
    limit = os.environ.get("OMP_NUM_THREADS", "")
    if limit.isdigit() and int(limit) > 0:
        cores = min(cores, int(limit))
    return max(1, cores)


def cgroup_cpu_quota(path: Path = Path("/sys/fs/cgroup/cpu.max")) -> int | None:
    """Whole CPUs the cgroup may use ("200000 100000" -> 2), None when unlimited."""
    try:
        quota, period = path.read_text().split()[:2]
        return None if quota == "max" else max(1, int(int(quota) // int(period)))
    except (OSError, ValueError):
        return None


def graph_path(owner: Path, kind: GraphKind, int8: str = "none") -> Path:
    """Where the graph of `kind` of checkpoint / model file `owner` is cached."""
    suffix = "" if int8 == "none" else f".int8-{int8}"
    owner = Path(owner)
    # "-", not ".": training removes its checkpoint's stale temporaries by the prefix
    # ".KEY.pt.", which would match a graph's temporary named ".KEY.pt.full.onnx.*".
    return owner.with_name(f"{owner.name}-{kind.name}{suffix}.onnx")


def file_digest(path: Path) -> str:
    """The first 16 hex digits of the SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:16]


def graph_home(owner: Path, cache_dir: Path | None) -> Path:
    """The name the graphs of checkpoint / model file `owner` are cached under
    (`graph_path(graph_home(...), kind)`).

    `owner` itself, graphs beside it, where no cache folder is given or `owner` lies
    in it (a checkpoint). Anything else (a model file) is keyed by its content:
    `cache_dir/graphs/<16 hex digits of its SHA-256>/<its name>`, so the model's own
    folder, which a robot may not be allowed to write, gets no file, and a model file
    replaced by another of the same name gets graphs of its own.
    """
    owner = Path(owner)
    if cache_dir is None:
        return owner
    cache = Path(cache_dir).expanduser().resolve()
    if owner.resolve().is_relative_to(cache):
        return owner
    home = cache / GRAPHS_FOLDER / file_digest(owner)
    # Unwritable: the graphs are then kept in memory, with one note (`rebuilt`).
    with contextlib.suppress(OSError):
        home.mkdir(parents=True, exist_ok=True)
    return home / owner.name


def adopt_shipped_graphs(owner: Path, home: Path) -> Path:
    """Copy into `home` the graphs kept beside `owner` that it lacks or holds other
    bytes of: the static int8 graphs task=relocalize keeps beside a model file (a robot
    has no map images to remake them). Each is checked when opened, as every cached
    graph is.

    Returns:
        Where the graphs are read and written: `home`, or `owner` itself where a graph
        kept beside it could not be copied into `home` (an unwritable cache), so the
        graphs beside the model file are read where they are.
    """
    if Path(owner) == Path(home):
        return home
    for kind in KINDS.values():
        for mode in INT8_MODES:
            shipped, cached_path = graph_path(owner, kind, mode), graph_path(home, kind, mode)
            if not shipped.is_file():
                continue
            data = shipped.read_bytes()
            # A cached copy of other bytes (damaged, or a stale file) is replaced.
            if cached_path.is_file() and cached_path.read_bytes() == data:
                continue
            try:
                write_graph(data, cached_path)
            except OSError:
                return owner
    return home


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
            beside it as OWNER-<kind>.onnx.
        calibration: map images (H x W x 3 uint8) for a static int8 mode.
        say: where notes go (a rebuilt graph and why).

    Raises:
        EngineUnavailableError: onnxruntime or onnx is missing, a graph does not match
            torch, or a needed graph cannot be written nor made in memory.
        ConfigError: a static int8 mode without calibration images and no cached graph.
    """
    options = options or EngineOptions()
    try:
        import onnx  # noqa: F401 - both are needed; say which one is missing
        import onnxruntime
    except ImportError as error:
        raise EngineUnavailableError(
            f'engine=onnx needs {error.name!r} (pip install "relocfw[onnx]")'
        ) from error
    if options.int8 == "static_8bit" and (why := cpu_flags.int8_saturation_reason()) is not None:
        raise EngineUnavailableError(why)
    source = trained_network(backbone)
    network = dropout_free_copy(source)
    fingerprint = weights_fingerprint(source)
    threads = int(options.threads or available_cores())
    open_session = session_opener(threads, options.spinning)
    sessions, scout = {}, None
    for kind in kinds_needed(source):
        session, data = float_graph(network, kind, owner, fingerprint, open_session, say)
        if options.int8 != "none" and (kind.name == "full" or not options.scout):
            quantised_session = int8_graph(
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
            if options.scout:
                scout = quantised_session
            else:
                session = quantised_session
        sessions[kind.name] = session
    precision = "float32" if options.int8 == "none" else f"int8 {options.int8}"
    if options.scout:
        precision = f"float32, int8 {options.int8} scout"
    description = f"onnxruntime {onnxruntime.__version__}, {precision}, {threads} threads"
    return OnnxBackbone(source, sessions, description, options.int8, scout)


def session_opener(threads: int, spinning: bool = False) -> Callable[[bytes | str], Any]:
    """A function opening an onnxruntime CPU session of a graph (its bytes or path)."""
    import onnxruntime

    session_options = onnxruntime.SessionOptions()
    session_options.intra_op_num_threads = threads
    session_options.inter_op_num_threads = 1
    session_options.add_session_config_entry(
        "session.intra_op.allow_spinning", "1" if spinning else "0"
    )

    def open_session(data: bytes | str) -> Any:
        cpu = ["CPUExecutionProvider"]
        return onnxruntime.InferenceSession(data, session_options, providers=cpu)

    return open_session


def cached(
    path: Path, open_session: Callable[[bytes | str], Any], why_not: Callable[[Any], str | None]
) -> tuple[Any, bytes, str | None]:
    """The cached graph at `path` if it serves: (session, bytes, None); else (None, b"",
    why it cannot: None when there is no file)."""
    if not path.is_file():
        return None, b"", None
    try:
        data = path.read_bytes()
        session = open_session(data)
    except Exception as error:  # onnxruntime's own types for an unreadable file
        return None, b"", f"it cannot be read ({type(error).__name__})"
    try:
        why = why_not(session)
    except DataError as error:
        why = str(error)
    except Exception as error:  # a graph that loads but fails to run
        why = f"it failed its check ({type(error).__name__}: {error})"
    return (session, data, None) if why is None else (None, b"", why)


def rebuilt(
    path: Path,
    build: Callable[[], tuple[Any, bytes]],
    stale: str | None,
    what: str,
    say: Callable[[str], None],
) -> tuple[Any, bytes]:
    """A fresh graph from `build`, written over `path`; one note when it replaced a
    `stale` file. EngineUnavailableError naming `path` when it cannot be built (the
    unusable cached file is removed, so later runs do not read it again)."""
    try:
        session, data = build()
    except Exception as error:  # the exporter's, quantiser's and onnxruntime's types
        cause = str(error) if isinstance(error, DataError) else f"{type(error).__name__}: {error}"
        if stale is not None:
            path.unlink(missing_ok=True)
            cause += f"; the cached file was unusable too ({stale}) and is removed"
        raise EngineUnavailableError(f"{path}: {what} failed: {cause}") from error
    try:
        write_graph(data, path)
    except OSError as error:
        say(f"note: cannot cache {path} ({error.strerror}); the graph is kept in memory")
    if stale is not None:
        say(f"note: rebuilt {path}: {stale}")
    return session, data


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

    def why_not(session: Any) -> str | None:
        stale = why_stale(session, kind, fingerprint)
        if stale is None:
            largest_difference(session, network, kind)  # DataError when it differs
        return stale

    session, data, stale = cached(path, open_session, why_not)
    if session is not None:
        return session, data

    def build() -> tuple[Any, bytes]:
        data = graph_bytes(network, kind, fingerprint, VERSION)
        session = open_session(data)
        largest_difference(session, network, kind)
        return session, data

    return rebuilt(path, build, stale, f"exporting the {kind.name} graph", say)


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
    """The int8 graph of `kind`: the cached file when it was quantised by today's
    recipe from today's float graph, else quantised anew."""
    path = graph_path(owner, kind, mode)
    source = hashlib.sha256(float_data).hexdigest()

    def why_not(session: Any) -> str | None:
        metadata = graph_metadata(session)
        stale = why_stale(session, kind, fingerprint)
        if stale is None and metadata.get(INT8_KEY) != mode:
            stale = f"it is int8 {metadata.get(INT8_KEY)!r}"
        if stale is None and metadata.get(RECIPE_KEY) != INT8_RECIPES[mode]:
            stale = "it was quantised by another recipe"
        if stale is None and metadata.get(FLOAT_KEY) != source:
            stale = "it was quantised from another float graph"
        return stale

    session, _, stale = cached(path, open_session, why_not)
    if session is not None:
        # Its metadata is what whoever wrote the file put there: only its answers can
        # show it is this model's quantisation. One that is not is refused, not remade:
        # it was tampered with (or damaged) after it was written.
        try:
            check_int8_answers(session, network, kind)
        except DataError as error:
            raise DataError(
                f"{path}: refused: {error}; a genuine int8 graph of this model stays within "
                "it: remove the file to have it quantised anew"
            ) from error
        return session
    if mode in STATIC_MODES and not calibration:
        raise ConfigError(
            f"onnx.int8={mode} calibrates on map images, and none are at hand here to "
            f"make {path}{f' ({stale})' if stale else ''}: run task=relocalize with "
            f"onnx.int8={mode} (it keeps the static graphs beside the model file it writes), "
            "or use onnx.int8=none"
        )

    def build() -> tuple[Any, bytes]:
        data = quantised(float_data, kind, mode, network, calibration, fingerprint)
        session = open_session(data)
        check_int8_answers(session, network, kind)
        return session, data

    session, _ = rebuilt(
        path, build, stale, f"int8 {mode} quantisation of the {kind.name} graph", say
    )
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

    with tempfile.TemporaryDirectory(prefix="relocfw-int8-") as folder:
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
                reduce_range=mode == "static",
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
            RECIPE_KEY: INT8_RECIPES[mode],
            FLOAT_KEY: hashlib.sha256(float_data).hexdigest(),
            "relocfw.version": VERSION,
        },
    )
    return graph.SerializeToString()


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


def check_int8_answers(session: Any, network: Backbone, kind: GraphKind) -> None:
    """DataError unless an int8 graph's answers on fresh check images are finite and
    within INT8_TOLERANCE of torch's float32 ones (`int8_deviations`)."""
    for name, deviation in int8_deviations(session, network, kind).items():
        if deviation > INT8_TOLERANCE[name]:
            unit = INT8_UNITS[name]
            raise DataError(
                f"the int8 {kind.name} graph's {name} lie {deviation:.3g} {unit} from torch's "
                f"float32 answers on fresh check images, beyond int8's {INT8_TOLERANCE[name]:g}"
            )


def int8_deviations(session: Any, network: Backbone, kind: GraphKind) -> dict[str, float]:
    """The largest deviation of each of a graph's outputs from torch's float32 answer on
    fresh check images (onnx_graphs.checked_answers), in INT8_UNITS; DataError for an
    answer that is not finite or of another shape."""
    deviations: dict[str, float] = {}
    try:
        for name, got, want, _ in checked_answers(session, network, kind):
            if got.shape != want.shape:
                raise DataError(
                    f"the int8 {kind.name} graph's {name} have shape {got.shape}, not {want.shape}"
                )
            if not np.all(np.isfinite(got)):
                raise DataError(f"the int8 {kind.name} graph's {name} are not finite")
            deviation = output_deviation(name, got, want, float(network.position_scale))
            deviations[name] = max(deviations.get(name, 0.0), deviation)
    except DataError:
        raise
    except Exception as error:  # onnxruntime's types, for a graph that fails to run
        raise DataError(
            f"the int8 {kind.name} graph fails to run ({type(error).__name__})"
        ) from error
    return deviations


def output_deviation(name: str, got: np.ndarray, want: np.ndarray, position_scale: float) -> float:
    """The largest deviation over a batch of answers `got` from `want`, in INT8_UNITS:
    positions in the network's own unit (position_scale metres: what it regresses),
    quaternions as the angle between the rotations (q and -q are one), descriptors
    and maps relative to the length of torch's."""
    if name == "positions":
        distances = np.linalg.norm(got - want, axis=1) / position_scale
    elif name == "quaternions":
        got, want = (q / np.linalg.norm(q, axis=1, keepdims=True) for q in (got, want))
        cosines = np.clip(np.abs(np.sum(got * want, axis=1)), 0.0, 1.0)
        distances = np.degrees(2.0 * np.arccos(cosines))
    else:
        got, want = got.reshape(len(got), -1), want.reshape(len(want), -1)
        lengths = np.maximum(np.linalg.norm(want, axis=1), 1e-12)
        distances = np.linalg.norm(got - want, axis=1) / lengths
    return float(np.max(distances))
