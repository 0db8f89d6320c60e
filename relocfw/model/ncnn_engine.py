"""engine=ncnn: a trained backbone's graphs run by ncnn, whose Winograd kernels do the
3 x 3 convolutions (two thirds of GoogLeNet's multiply-adds) in fewer multiplies
than a direct float32 engine can (docs/engine.md measures what that buys).

The checked float ONNX graphs of relocfw.model.onnx_engine (cached beside the
checkpoint or model file `owner`) are converted by pnnx, ncnn's converter, into
`OWNER-<kind>.ncnn.param` and `.ncnn.bin`, with `OWNER-<kind>.ncnn.json` recording
which ONNX graph they came from, the two files' hashes and the ncnn and pnnx
versions. A set whose record is missing, unreadable, of another ONNX graph, of other
files or of other versions, or whose network answers differently from torch on
fresh check images (relocfw.model.onnx_graphs.check_images: the record is its
writer's word, the answers are checked), is converted again (one note), never used.
Every network, cached or fresh, first runs once in a process of its own (the probe
in relocfw.model.ncnn_session): ncnn is C++, and a network it mishandles on this CPU
crashes that process, not the user's run. ncnn loads only its
own layer types from a .param file: nothing a file names is imported or run.

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
from relocfw.model import ncnn_session
from relocfw.model.ncnn_session import NcnnComputeError, NcnnLoadError, NcnnSession
from relocfw.model.onnx_backbone import OnnxBackbone, trained_network
from relocfw.model.onnx_engine import (
    EngineOptions,
    EngineUnavailableError,
    available_cores,
    float_graph,
    graph_path,
    session_opener,
)
from relocfw.model.onnx_export import dropout_free_copy, weights_fingerprint
from relocfw.model.onnx_graphs import GraphKind, kinds_needed, largest_difference

# Raised when what the files hold, or how they are made, changes meaning.
NCNN_FORMAT = "1"
CONVERSION_SECONDS = 600
PROBE = Path(ncnn_session.__file__)


def ncnn_files(owner: Path, kind: GraphKind) -> dict[str, Path]:
    """Where the ncnn network of `kind` of checkpoint / model file `owner` is cached:
    its layers (param), weights (bin) and record (json)."""
    graph = graph_path(owner, kind)  # OWNER-<kind>.onnx: the same naming rule
    return {part: graph.with_suffix(f".ncnn.{part}") for part in ("param", "bin", "json")}


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
    if options.int8 != "none" or options.spinning:
        raise EngineUnavailableError("onnx.int8 and onnx.spinning are onnxruntime's, not ncnn's")
    try:
        import ncnn  # noqa: F401
        import onnx  # noqa: F401 - the ONNX graphs pnnx converts are made and checked first
        import onnxruntime  # noqa: F401
        import pnnx  # noqa: F401
    except ImportError as error:
        # A package that is there but cannot load (a missing library) says why too.
        missing = error.name in ("ncnn", "onnx", "onnxruntime", "pnnx")
        why = "" if missing else f": {error}"
        raise EngineUnavailableError(
            f'engine=ncnn needs {error.name!r}{why} (pip install "relocfw[ncnn]")'
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
    description = f"ncnn {versions()['ncnn']}, float32, {threads} threads"
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
    side = int(network.input_size)
    stale = None
    if any(path.exists() for path in files.values()):
        stale = why_not_cached(files, wanted)
        if stale is None:
            try:
                return checked(files["param"], files["bin"], network, kind, threads)
            except DataError as error:
                stale = str(error)
    with tempfile.TemporaryDirectory(prefix="relocfw-ncnn-") as folder:
        try:
            param, weights = converted(onnx_data, kind, side, Path(folder))
            session = checked(param, weights, network, kind, threads)
        except DataError as error:
            cause = str(error)
            if stale is not None:
                for path in files.values():
                    path.unlink(missing_ok=True)
                cause += f"; the cached files were unusable too ({stale}) and are removed"
            raise EngineUnavailableError(
                f"{files['param']}: converting the {kind.name} graph for ncnn failed: {cause}"
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


def checked(
    param: Path, weights: Path, network: Backbone, kind: GraphKind, threads: int
) -> NcnnSession:
    """The network of these files, opened once it has run in the probe process and
    answered as torch does here; DataError saying why not."""
    survives_a_run(param, weights, kind, int(network.input_size), threads)
    try:
        session = NcnnSession(param, weights, kind.outputs, threads)
        largest_difference(session, network, kind)
    except (NcnnLoadError, NcnnComputeError) as error:
        raise DataError(str(error)) from error
    return session


def why_not_cached(files: dict[str, Path], onnx_sha256: str) -> str | None:
    """None when the cached files are whole, made from this ONNX graph by today's
    ncnn and pnnx; else why they cannot serve."""
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
    if record.get("versions") != versions():
        return "it was converted with other ncnn / pnnx versions"
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
    if kind.any_size:  # a second shape, both sides changed, tells pnnx which axes vary
        command.append(f"inputshape2=[1,3,{side + 7},{side + side // 2 + 1}]f32")
    done = finished(command, folder, "pnnx")
    if done.returncode != 0:
        raise DataError(f"pnnx exited with {done.returncode}: {last_words(done, 3)}")
    if not (param.is_file() and weights.is_file()):
        raise DataError(f"pnnx wrote no ncnn files: {last_words(done, 3)}")
    return param, weights


def finished(command: list[str], folder: Path, what: str) -> subprocess.CompletedProcess:
    """`command` run to its end in `folder`; DataError when it cannot start or hangs."""
    try:
        return subprocess.run(
            command,
            cwd=folder,
            capture_output=True,
            text=True,
            errors="replace",
            timeout=CONVERSION_SECONDS,
        )
    except (OSError, subprocess.TimeoutExpired) as error:
        raise DataError(f"{what} did not run to its end ({error})") from error


def last_words(done: subprocess.CompletedProcess, lines: int) -> str:
    said = (done.stderr or done.stdout).strip().splitlines()[-lines:]
    return " | ".join(said) or "it said nothing"


def survives_a_run(param: Path, weights: Path, kind: GraphKind, side: int, threads: int) -> None:
    """DataError unless the network runs on every check size, on `threads` cores, in
    a process of its own (relocfw.model.ncnn_session's probe): a crash there is
    reported, not suffered."""
    sizes = [f"{height},{width}" for height, width in kind.check_sizes(side)]
    # -P (-I before Python 3.11): the probe's folder, relocfw/model, is not put on the
    # path, where a module could shadow one that numpy or ncnn import.
    isolated = "-P" if sys.version_info >= (3, 11) else "-I"
    command = [sys.executable, isolated, str(PROBE), str(param), str(weights)]
    command += [str(len(kind.outputs)), str(threads), *sizes]
    done = finished(command, param.parent, "the probe run")
    if done.returncode < 0:
        signals = {s.value: s.name for s in signal.Signals}
        name = signals.get(-done.returncode, f"signal {-done.returncode}")
        raise DataError(f"ncnn crashed ({name}) running the converted network")
    if done.returncode != 0:
        raise DataError(f"the converted network failed its probe run: {last_words(done, 1)}")


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
    """The installed ncnn and pnnx (what the record names; "" for one not installed)."""
    import importlib.metadata

    found = {}
    for name in ("ncnn", "pnnx"):
        try:
            found[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            found[name] = ""
    return found


def ncnn_installed() -> bool:
    """Whether engine=ncnn's packages are installed (without importing them)."""
    import importlib.util

    return all(importlib.util.find_spec(name) is not None for name in ("ncnn", "pnnx"))
