"""engine=ncnn: a trained backbone's graphs run by ncnn, whose Winograd kernels do the
3 x 3 convolutions (two thirds of GoogLeNet's multiply-adds) in fewer multiplies
than a direct float32 engine can (docs/engine.md measures what that buys).

The checked float ONNX graphs of relocfw.model.onnx_engine (cached beside the
checkpoint or model file `owner`) are converted by pnnx, ncnn's converter, into
`OWNER-<kind>.ncnn.param` and `.ncnn.bin`, with `OWNER-<kind>.ncnn.json` recording
which ONNX graph they came from and the two files' hashes. A set whose record is
missing, unreadable, of another ONNX graph or of other files, or whose network
answers differently from torch on the check images, is converted again (one note),
never used. ncnn loads only its own layer types from a .param file: nothing a file
names is imported or run.

ncnn takes one image per pass; the batch is run image by image, each pass on
`threads` cores. Weights and arithmetic stay float32 (ncnn's fp16 / bf16 storage is
turned off), so answers are torch's to the engine tolerance.
"""

from __future__ import annotations

import hashlib
import json
import signal
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

from relocfw.core.atomic_files import atomic_write
from relocfw.core.errors import DataError
from relocfw.core.interfaces import Backbone
from relocfw.model.ncnn_session import NcnnLoadError, NcnnSession
from relocfw.model.onnx_backbone import OnnxBackbone, trained_network
from relocfw.model.onnx_engine import (
    EngineOptions,
    EngineUnavailableError,
    available_cores,
    float_graph,
    session_opener,
)
from relocfw.model.onnx_export import dropout_free_copy, weights_fingerprint
from relocfw.model.onnx_graphs import GraphKind, kinds_needed, largest_difference

# Raised when what the files hold, or how they are made, changes meaning.
NCNN_FORMAT = "1"
CONVERSION_SECONDS = 600
PROBE = Path(__file__).with_name("ncnn_probe.py")


def ncnn_files(owner: Path, kind: GraphKind) -> dict[str, Path]:
    """Where the ncnn network of `kind` of checkpoint / model file `owner` is cached:
    its layers (param), weights (bin) and record (json)."""
    owner = Path(owner)
    return {
        part: owner.with_name(f"{owner.name}-{kind.name}.ncnn.{part}")
        for part in ("param", "bin", "json")
    }


def ncnn_engine(
    backbone: Backbone,
    owner: Path,
    options: EngineOptions | None = None,
    say: Callable[[str], None] = print,
) -> OnnxBackbone:
    """`backbone` run by ncnn, its networks cached beside `owner`.

    Args:
        backbone: the trained torch backbone (or an engine's: its source is used).
        owner: the checkpoint or model file the weights come from.
        options: `threads` (None: the cores available); int8 is onnxruntime's only.
        say: where notes go (a rebuilt file and why).

    Raises:
        EngineUnavailableError: ncnn, pnnx, onnx or onnxruntime is missing, pnnx cannot
            convert a graph, or ncnn's answers do not match torch's.
    """
    options = options or EngineOptions()
    if options.int8 != "none":
        raise EngineUnavailableError(f"onnx.int8={options.int8} is onnxruntime's, not ncnn's")
    try:
        import ncnn
        import onnx  # noqa: F401 - the ONNX graphs pnnx converts are made and checked first
        import onnxruntime  # noqa: F401
        import pnnx  # noqa: F401
    except ImportError as error:
        raise EngineUnavailableError(
            f'engine=ncnn needs {error.name!r} (pip install "relocfw[ncnn]")'
        ) from error
    source = trained_network(backbone)
    network = dropout_free_copy(source)
    fingerprint = weights_fingerprint(source)
    threads = int(options.threads or available_cores())
    # The ONNX graphs are checked with one onnxruntime thread: they are only converted.
    open_onnx = session_opener(1)
    sessions = {}
    for kind in kinds_needed(source):
        _, onnx_data = float_graph(network, kind, owner, fingerprint, open_onnx, say)
        sessions[kind.name] = ncnn_network(network, kind, owner, onnx_data, threads, say)
    description = f"ncnn {ncnn.__version__}, float32, {threads} threads"
    return OnnxBackbone(source, sessions, description)


def ncnn_network(
    network: Backbone,
    kind: GraphKind,
    owner: Path,
    onnx_data: bytes,
    threads: int,
    say: Callable[[str], None],
) -> NcnnSession:
    """The checked ncnn network of `kind`: the cached files, or a fresh conversion of
    the ONNX graph `onnx_data` written over them."""
    files = ncnn_files(owner, kind)
    wanted = hashlib.sha256(onnx_data).hexdigest()
    stale = why_not_cached(files, wanted)
    if stale is None:
        try:
            session = opened(files["param"], files["bin"], kind, threads)
            largest_difference(session, network, kind)
            return session
        except DataError as error:
            stale = str(error)
    elif stale == "":
        stale = None  # nothing cached: a first conversion, no note
    with tempfile.TemporaryDirectory(prefix="relocfw-ncnn-") as folder:
        try:
            side = int(network.input_size)
            param, weights = converted(onnx_data, kind, side, Path(folder))
            survives_a_run(param, weights, kind, side)
            session = opened(param, weights, kind, threads)
            largest_difference(session, network, kind)
        except DataError as error:
            if stale is not None:
                for path in files.values():
                    path.unlink(missing_ok=True)
            raise EngineUnavailableError(
                f"{files['param']}: converting the {kind.name} graph for ncnn failed: {error}"
            ) from error
        # ncnn has read both files: the session outlives the temporary folder.
        try:
            keep(param, weights, files, wanted)
        except OSError as error:
            say(f"note: cannot cache {files['param']} ({error.strerror}); kept in memory")
            return session
    if stale is not None:
        say(f"note: rebuilt {files['param']}: {stale}")
    return session


def opened(param: Path, weights: Path, kind: GraphKind, threads: int) -> NcnnSession:
    try:
        return NcnnSession(param, weights, kind.outputs, threads)
    except NcnnLoadError as error:
        raise DataError(str(error)) from error


def why_not_cached(files: dict[str, Path], onnx_sha256: str) -> str | None:
    """None when the cached files are whole and made from this ONNX graph; "" when
    there are none; else why they cannot serve."""
    if not any(path.exists() for path in files.values()):
        return ""
    try:
        record = json.loads(files["json"].read_text())
        param_sha, bin_sha = (hash_of(files[part]) for part in ("param", "bin"))
    except (OSError, ValueError) as error:
        return f"it cannot be read ({type(error).__name__})"
    if not isinstance(record, dict) or record.get("format") != NCNN_FORMAT:
        return "it is of another format"
    if record.get("onnx_sha256") != onnx_sha256:
        return "it was converted from another ONNX graph"
    if record.get("param_sha256") != param_sha or record.get("bin_sha256") != bin_sha:
        return "its files are not the ones converted"
    if record.get("versions") != versions():  # probed with other code
        return "it was converted and probed with other ncnn / pnnx versions"
    return None


def hash_of(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def converted(onnx_data: bytes, kind: GraphKind, side: int, folder: Path) -> tuple[Path, Path]:
    """pnnx's conversion of an ONNX graph into ncnn's two files, in `folder`.
    DataError with pnnx's last words when it fails."""
    import pnnx

    source = folder / "graph.onnx"
    source.write_bytes(onnx_data)
    param, weights = folder / "graph.ncnn.param", folder / "graph.ncnn.bin"
    command = [
        pnnx.EXEC_PATH,
        str(source),
        f"inputshape=[1,3,{side},{side}]f32",
        "fp16=0",  # float32 weights: the answers must be torch's
        f"ncnnparam={param}",
        f"ncnnbin={weights}",
    ]
    # pnnx's other outputs (its own graph, Python scripts) go to the temporary folder.
    for part in ("pnnxparam", "pnnxbin", "pnnxpy", "pnnxonnx", "ncnnpy"):
        command.append(f"{part}={folder / part}")
    if kind.any_size:  # a second shape tells pnnx which axes vary
        command.append(f"inputshape2=[1,3,{side},{side + side // 3 + 5}]f32")
    try:
        done = subprocess.run(
            command, cwd=folder, capture_output=True, text=True, timeout=CONVERSION_SECONDS
        )
    except (OSError, subprocess.TimeoutExpired) as error:
        raise DataError(f"pnnx did not run ({type(error).__name__}: {error})") from error
    if done.returncode != 0 or not (param.is_file() and weights.is_file()):
        last = " | ".join((done.stderr or done.stdout).strip().splitlines()[-3:])
        raise DataError(f"pnnx exited with {done.returncode}: {last}")
    return param, weights


def survives_a_run(param: Path, weights: Path, kind: GraphKind, side: int) -> None:
    """DataError unless the converted network runs on every check size in a process
    of its own (relocfw.model.ncnn_probe): a crash there is reported, not suffered."""
    sizes = [f"{height},{width}" for height, width in kind.check_sizes(side)]
    # The probe runs as a script, not as part of relocfw: it needs ncnn and numpy only,
    # and starts in a tenth of a second instead of the two that importing torch takes.
    command = [sys.executable, str(PROBE), str(param), str(weights)]
    command += [str(len(kind.outputs)), *sizes]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=CONVERSION_SECONDS)
    except (OSError, subprocess.TimeoutExpired) as error:
        raise DataError(f"the probe run did not finish ({type(error).__name__})") from error
    if done.returncode < 0:
        name = signal.Signals(-done.returncode).name
        raise DataError(f"ncnn crashed ({name}) running the converted network")
    if done.returncode != 0:
        last = " | ".join(done.stderr.strip().splitlines()[-2:])
        raise DataError(f"the converted network failed its probe run: {last}")


def keep(param: Path, weights: Path, files: dict[str, Path], onnx_sha256: str) -> None:
    """Write the converted files beside the owner; the record last, so a run killed
    on the way leaves files whose hashes the record does not hold (converted again)."""
    record = {
        "format": NCNN_FORMAT,
        "onnx_sha256": onnx_sha256,
        "param_sha256": hash_of(param),
        "bin_sha256": hash_of(weights),
        "versions": versions(),
    }
    files["json"].unlink(missing_ok=True)
    for part, made in (("param", param), ("bin", weights)):
        with atomic_write(files[part], "wb") as stream:
            stream.write(made.read_bytes())
    with atomic_write(files["json"], "w") as stream:
        stream.write(json.dumps(record, indent=1) + "\n")


def versions() -> dict[str, str]:
    import importlib.metadata

    return {name: importlib.metadata.version(name) for name in ("ncnn", "pnnx")}
