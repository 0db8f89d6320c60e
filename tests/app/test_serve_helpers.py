"""What the serve tests share: a tiny model file, images, and a real service started
as a subprocess on a free port (no tests here).

Run as a script, this file is a service whose queries wait at a gate: a query writes
`started-N` into the gate folder, then waits until the folder holds `open`. The tests
of the queue, of disconnecting clients and of SIGTERM use it to hold a query in
flight for exactly as long as they need.
"""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import httpx
import numpy as np

HERE = Path(__file__).resolve()
# Small enough to reach with a test body; large enough for the test images.
MAX_BYTES = 200_000
MAX_PIXELS = 1_000_000
START_SECONDS = 120.0


def tiny_model(folder: Path) -> Path:
    """A 32-pixel PoseNet with a two-image map; it samples two windows per answer
    (crop_samples), so answers carry a spread as their uncertainty signal."""
    import torch

    from relocfw import QueryOptions, Relocalizer
    from relocfw.model.model_file import save_model
    from relocfw.plugins.exhaustive_index import ExhaustiveIndex
    from relocfw.plugins.posenet import PoseNet
    from relocfw.plugins.sweep_crop import SweepCrop

    torch.manual_seed(0)
    backbone = PoseNet(input_size=32, width=0.125, feature_dim=32)
    backbone.set_crop_scale(1.142857)  # crop sampling needs a crop larger than the view
    options = QueryOptions(crop_samples=2, sample_seed=7)
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), SweepCrop(), options)
    relocalizer.fit([np.zeros((36, 48, 3), np.uint8), np.full((36, 48, 3), 200, np.uint8)])
    parts = {"backbone": {"input_size": 32, "width": 0.125, "feature_dim": 32}}
    return save_model(folder / "model.relocfw", relocalizer, parts, {"dataset": "synthetic"})


def pixels(seed: int, height: int = 36, width: int = 48) -> np.ndarray:
    """H x W x 3 uint8 RGB noise, the same for the same seed."""
    return np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)


def png_of(image: np.ndarray) -> bytes:
    """PNG bytes of RGB (or RGBA, or grey) pixels."""
    if image.ndim == 3 and image.shape[2] >= 3:
        image = np.concatenate([image[:, :, 2::-1], image[:, :, 3:]], axis=2)
    ok, data = cv2.imencode(".png", image)
    assert ok
    return data.tobytes()


def jpeg_of(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".jpg", np.ascontiguousarray(image[:, :, ::-1]))
    assert ok
    return data.tobytes()


@dataclass
class Server:
    """A running service: its process, URL and the file its stderr goes to."""

    process: subprocess.Popen
    url: str
    log: Path

    def client(self, **options: object) -> httpx.Client:
        return httpx.Client(base_url=self.url, timeout=30.0, **options)

    def stop(self) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
        return self.process.wait(timeout=60)


def first_line(process: subprocess.Popen, seconds: float) -> str:
    """The process's first line of stdout, or "" when it ends or takes too long."""
    lines: queue.Queue[str] = queue.Queue()
    reader = threading.Thread(target=lambda: lines.put(process.stdout.readline()), daemon=True)
    reader.start()
    try:
        return lines.get(timeout=seconds)
    except queue.Empty:
        return ""


def start_server(
    command: list[str], folder: Path, preexec_fn: Callable[[], None] | None = None
) -> Server:
    """Start a service (`command` ends with its overrides) on a free port (serve.port=0:
    it prints the URL it listens on) and wait until it answers /v1/health.
    `preexec_fn` runs in the child before the service (e.g. to lower its limits)."""
    log = folder / "server.log"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    with open(log, "w") as errors:
        process = subprocess.Popen(
            [*command, "serve.port=0", "engine=torch", "quiet=true"],
            stdout=subprocess.PIPE,
            stderr=errors,
            text=True,
            env=env,
            cwd=folder,
            # Its own process group: stopping it stops its worker processes too
            # (serve.workers > 1), which would otherwise outlive the test.
            start_new_session=True,
            preexec_fn=preexec_fn,
        )
    line = first_line(process, START_SECONDS)
    if not line.startswith("relocfw serve: http://"):
        stop(process)
        raise AssertionError(f"the service did not start: {line!r}\n{log.read_text()}")
    url = line.split()[2]
    for _ in range(200):
        try:
            if httpx.get(f"{url}/v1/health", timeout=5).status_code == 200:
                return Server(process, url, log)
        except httpx.TransportError:
            time.sleep(0.05)
    stop(process)
    raise AssertionError(f"the service never answered /v1/health:\n{log.read_text()}")


def stop(process: subprocess.Popen) -> None:
    """Stop a service as a user would (SIGTERM: it stops its workers), and whatever
    of its process group is still there after 10 s by SIGKILL."""
    if process.poll() is None:
        process.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=10)
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(process.pid, signal.SIGKILL)  # workers left behind, if any
    process.wait(timeout=30)


def serve_command(model: Path, *overrides: str) -> list[str]:
    """`relocfw-serve MODEL ...` as a module run (the console script may not be
    installed in a development checkout)."""
    return [sys.executable, "-m", "relocfw.app.tasks.serve", str(model), *overrides]


def gated_command(model: Path, gate: Path, *overrides: str) -> list[str]:
    return [sys.executable, str(HERE), str(model), str(gate), *overrides]


@contextmanager
def running(command: list[str], folder: Path) -> Iterator[Server]:
    server = start_server(command, folder)
    try:
        yield server
    finally:
        stop(server.process)
        server.process.stdout.close()


def wait_for(condition, seconds: float = 20.0, what: str = "the condition") -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


class Gated:
    """A Relocalizer whose queries wait at a gate folder (see the module's docstring);
    everything else is the wrapped Relocalizer's."""

    def __init__(self, inner: object, gate: Path) -> None:
        self.inner = inner
        self.gate = gate
        self.started = 0

    def __getattr__(self, name: str) -> object:
        return getattr(self.inner, name)

    def localize(self, image, camera=None, name=None):
        self.started += 1
        (self.gate / f"started-{self.started}").touch()
        while not (self.gate / "open").exists():
            time.sleep(0.01)
        return self.inner.localize(image, camera=camera, name=name)


def serve_gated(model: str, gate: str, overrides: list[str]) -> None:
    """relocfw-serve MODEL with every query waiting at `gate`."""
    from relocfw.app.tasks import serve

    load = serve.load_for_serve
    serve.load_for_serve = lambda config, device: Gated(load(config, device), Path(gate))
    serve.main([model, *overrides])


if __name__ == "__main__":
    serve_gated(sys.argv[1], sys.argv[2], sys.argv[3:])
