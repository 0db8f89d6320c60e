"""relocfw serve under load: a real service process on a free port and real HTTP
clients (httpx, async), N concurrent clients each sending a fixed number of queries.

For each model and each client count: throughput (answers per second of wall time),
p50 / p99 latency as the client sees it, the 503s (each retried after its
Retry-After, so none is lost to them), and every answer compared with what
`relocfw task=localize` answers for the same frame (none lost, none different). One
more row per model runs the most clients again with `--slow-clients` silent slow
clients held open beside them (each sends its headers with Content-Length: 100000 and
then nothing, and comes back whenever the service closes it), so its throughput and
p99 say what such clients cost the good ones. The JSON records what each model runs:
the model file's query options and parts (the refine plugin and its options among
them), what the service says it runs (/v1/model), and the serve settings it ran with.
Writes JSON atomically and prints a markdown table.

    .venv/bin/python benchmarks/serve_load.py \
        --model features=outputs/DATE/TIME/model.relocfw \
        --model posenet=outputs/DATE/TIME/model.relocfw \
        --frames '../shared/data/7scenes-redkitchen/redkitchen/seq-03/frame-*.color.png' \
        --limit 64 --clients 1 2 4 8 --queries 16 --slow-clients 8 \
        --out benchmarks/results/serve_load.json

`--smoke` runs the whole path on a tiny synthetic model and six generated frames in a
few seconds (the numbers mean nothing): what the tests run.
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import glob
import json
import math
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

START_SECONDS = 300.0
# A silent slow client: a whole request head announcing a body it never sends.
SILENT_HEAD = (
    "POST /v1/localize HTTP/1.1\r\nHost: {host}\r\nContent-Type: image/png\r\n"
    "Content-Length: 100000\r\n\r\n"
)
# Bounds on a slow client's comebacks (each after the service closed it).
MOST_COMEBACKS = 1000


@dataclass
class Served:
    """One answered (or lost) query."""

    frame: Path
    ms: float
    answer: dict | None
    refusals: int


@dataclass
class Reference:
    """task=localize's pose of each frame: (x, y, z, qw, qx, qy, qz)."""

    poses: dict[str, np.ndarray] = field(default_factory=dict)


def frame_name(index: int) -> str:
    """The frame name task=localize gives frame `index` (its link's folder and stem),
    sent along so a refiner that reads names sees the same ones."""
    return f"frames/{index:06d}"


def reference_poses(model: Path, frames: list[Path], work: Path, overrides: list[str]) -> Reference:
    """Run `relocfw task=localize` over the frames (a folder of links to them) and read
    its localization.csv."""
    folder = work / "frames"
    folder.mkdir(parents=True, exist_ok=True)
    for index, frame in enumerate(frames):
        link = work / f"{frame_name(index)}{frame.suffix}"
        if not link.exists():
            link.symlink_to(frame.resolve())
    run_dir = work / "localize"
    command = [
        sys.executable,
        "-m",
        "relocfw",
        "task=localize",
        f"localize.model={model}",
        f"localize.images={folder}",
        "quiet=true",
        f"hydra.run.dir={run_dir}",
        *overrides,
    ]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"task=localize failed:\n{done.stderr[-3000:]}")
    found = Reference()
    with open(run_dir / "localization.csv") as stream:
        for row in csv.DictReader(stream):
            index = int(Path(row["image"]).stem)
            pose = [float(row[key]) for key in ("x", "y", "z", "qw", "qx", "qy", "qz")]
            found.poses[str(frames[index])] = np.array(pose)
    return found


def start_service(model: Path, overrides: list[str], log: Path) -> tuple[subprocess.Popen, str]:
    """`relocfw-serve MODEL serve.port=0 ...` and the URL it prints."""
    serve = [sys.executable, "-m", "relocfw.app.tasks.serve"]
    command = [*serve, str(model), "serve.port=0", "quiet=true"]
    with open(log, "w") as errors:
        process = subprocess.Popen(
            [*command, *overrides], stdout=subprocess.PIPE, stderr=errors, text=True
        )
    started = time.monotonic()
    line = process.stdout.readline()
    if not line.startswith("relocfw serve: http://"):
        process.kill()
        raise SystemExit(f"the service did not start:\n{log.read_text()[-3000:]}")
    print(f"service up in {time.monotonic() - started:.1f} s: {line.split()[2]}", flush=True)
    return process, line.split()[2]


def stop_service(process: subprocess.Popen) -> int:
    process.send_signal(signal.SIGTERM)
    return process.wait(timeout=120)


async def one_query(client, frame: Path, body: bytes, name: str) -> Served:
    """POST one frame; a 503 is retried after its Retry-After (counted, never lost)."""
    content_type = "image/png" if body.startswith(b"\x89PNG") else "image/jpeg"
    params = {"name": name}
    refusals = 0
    started = time.perf_counter()
    while True:
        response = await client.post(
            "/v1/localize", content=body, params=params, headers={"Content-Type": content_type}
        )
        if response.status_code != 503:
            break
        refusals += 1
        await asyncio.sleep(float(response.headers.get("retry-after", "1")))
    ms = 1000.0 * (time.perf_counter() - started)
    answer = response.json() if response.status_code == 200 else None
    return Served(frame, ms, answer, refusals)


@dataclass
class SlowClients:
    """What the silent slow clients of a round met: each close by the service is one
    comeback; `timeouts` are the closes that came with a 408."""

    comebacks: int = 0
    timeouts: int = 0


async def silent_client(url: str, found: SlowClients, stop: asyncio.Event) -> None:
    """Hold one silent request open until `stop`: headers, then nothing; when the
    service answers (408) and closes it, open another (at most MOST_COMEBACKS)."""
    from urllib.parse import urlparse

    address = urlparse(url)
    head = SILENT_HEAD.format(host=address.netloc).encode()
    for _ in range(MOST_COMEBACKS):
        reader, writer = await asyncio.open_connection(address.hostname, address.port)
        try:
            writer.write(head)
            await writer.drain()
            closed = asyncio.ensure_future(reader.read())
            stopped = asyncio.ensure_future(stop.wait())
            await asyncio.wait({closed, stopped}, return_when=asyncio.FIRST_COMPLETED)
            stopped.cancel()
            if not closed.done():
                closed.cancel()
                return
            found.comebacks += 1
            found.timeouts += closed.result().startswith(b"HTTP/1.1 408")
        finally:
            writer.close()


async def load_round(
    url: str, clients: int, queries: int, frames: list[Path], slow: int = 0
) -> tuple:
    """`clients` concurrent clients, each sending `queries` frames in turn (client i
    starts at frame i * queries, cycling), with `slow` silent slow clients open the
    whole time; the served queries, the wall seconds and what the slow ones met."""
    import httpx

    bodies = {frame: frame.read_bytes() for frame in frames}
    stop = asyncio.Event()
    met = SlowClients()
    holding = [asyncio.ensure_future(silent_client(url, met, stop)) for _ in range(slow)]
    await asyncio.sleep(0.5 if slow else 0.0)  # the service has read their heads

    async def client_run(number: int) -> list[Served]:
        found = []
        async with httpx.AsyncClient(base_url=url, timeout=600.0) as client:
            for k in range(queries):
                index = (number * queries + k) % len(frames)
                frame = frames[index]
                found.append(await one_query(client, frame, bodies[frame], frame_name(index)))
        return found

    started = time.perf_counter()
    try:
        runs = await asyncio.gather(*(client_run(n) for n in range(clients)))
    finally:
        seconds = time.perf_counter() - started
        stop.set()
        await asyncio.gather(*holding)
    return [served for run in runs for served in run], seconds, met


def percentile(values: list[float], share: float) -> float:
    return float(np.percentile(values, share)) if values else math.nan


def compare(served: list[Served], reference: Reference) -> dict:
    """Lost (no 200), different (beyond 1e-6 of task=localize's pose) and the largest
    differences."""
    position, quaternion, different = 0.0, 0.0, 0
    for item in served:
        if item.answer is None:
            continue
        expected = reference.poses[str(item.frame)]
        got = np.array([*item.answer["position"], *item.answer["quaternion"]])
        position = max(position, float(np.abs(got[:3] - expected[:3]).max()))
        quaternion = max(quaternion, float(np.abs(got[3:] - expected[3:]).max()))
        different += not np.allclose(got, expected, rtol=0, atol=1e-6)
    return {
        "lost": sum(item.answer is None for item in served),
        "different": different,
        "max_position_difference": position,
        "max_quaternion_difference": quaternion,
    }


def json_safe(value: object) -> object:
    """Plain JSON values of a model file's options (paths and the like as text)."""
    return json.loads(json.dumps(value, default=str))


def model_file_settings(model: Path) -> dict:
    """What the model file stores besides its weights and map: the query options and
    each part's class and options (the refine plugin's among them), and its metadata."""
    from relocfw.model.checkpoints import read_torch_file
    from relocfw.model.older_formats import stored_options

    payload = read_torch_file(model, "model")
    parts = {}
    for part in ("backbone", "index", "crop", "refine"):
        entry = payload.get(part)
        parts[part] = (
            None if entry is None else {"class": entry["class"], "options": entry["options"]}
        )
    return json_safe(
        {
            "format": payload.get("format"),
            "query": stored_options(payload, model),
            **parts,
            "error_bounds": "error_bounds" in payload,
            "metadata": payload.get("metadata", {}),
        }
    )


def serve_settings(model: Path, overrides: list[str]) -> dict:
    """The serve.* values, the engine and the query.* values set, as the service
    composes them from the same overrides."""
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    from relocfw.app.config_schema import store
    from relocfw.app.hydra_plugins import install

    store()
    install()
    with initialize_config_module(config_module="relocfw.conf", version_base="1.3"):
        cfg = compose("config", overrides=["task=serve", f"serve.model={model}", *overrides])
    values = OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
    query = {key: value for key, value in values["query"].items() if value is not None}
    return json_safe({"serve": values["serve"], "engine": values["engine"], "query": query})


def service_model(url: str) -> dict:
    """GET /v1/model: what the running service says it runs."""
    import httpx

    return httpx.get(f"{url}/v1/model", timeout=60).json()


def round_row(name: str, clients: int, slow: int, result: tuple, reference: Reference) -> dict:
    served, seconds, met = result
    latencies = [s.ms for s in served if s.answer is not None]
    server_ms = [s.answer["ms"]["total"] for s in served if s.answer is not None]
    return {
        "model": name,
        "clients": clients,
        "slow_clients": slow,
        "queries": len(served),
        "answered": len(latencies),
        "throughput_per_s": len(latencies) / seconds,
        "p50_ms": percentile(latencies, 50),
        "p99_ms": percentile(latencies, 99),
        "server_p50_ms": percentile(server_ms, 50),
        "refused_503": sum(s.refusals for s in served),
        "slow_comebacks": met.comebacks,
        "slow_408s": met.timeouts,
        **compare(served, reference),
    }


def measure_model(
    name: str, model: Path, frames: list[Path], args: argparse.Namespace, work: Path
) -> tuple[list[dict], dict]:
    """The model's rows, and what it ran with (model file, service, serve settings)."""
    overrides = list(args.override)
    reference = reference_poses(model, frames, work / name, overrides)
    serve_overrides = [*overrides, *args.serve_override]
    settings = {
        "file": str(model),
        "model_file": model_file_settings(model),
        "serve_settings": serve_settings(model, serve_overrides),
    }
    process, url = start_service(model, serve_overrides, work / f"{name}-serve.log")
    rows = []
    try:
        settings["service"] = service_model(url)
        asyncio.run(load_round(url, 1, 1, frames[:1]))  # warm: first decode, first pass
        rounds = [(clients, 0) for clients in args.clients]
        if args.slow_clients:
            rounds.append((max(args.clients), args.slow_clients))
        for clients, slow in rounds:
            result = asyncio.run(load_round(url, clients, args.queries, frames, slow))
            rows.append(round_row(name, clients, slow, result, reference))
            print(table_line(rows[-1]), flush=True)
    finally:
        exit_status = stop_service(process)
    if exit_status != 0:
        raise SystemExit(f"the service exited {exit_status} on SIGTERM (expected 0)")
    return rows, settings


TABLE_HEAD = (
    "| model | clients | answered | lost | different | per s | p50 ms | p99 ms | 503s |\n"
    "|---|---:|---:|---:|---:|---:|---:|---:|---:|"
)


def table_line(row: dict) -> str:
    slow = row.get("slow_clients", 0)
    clients = f"{row['clients']} + {slow} slow" if slow else str(row["clients"])
    return (
        f"| {row['model']} | {clients} | {row['answered']}/{row['queries']} | "
        f"{row['lost']} | {row['different']} | {row['throughput_per_s']:.2f} | "
        f"{row['p50_ms']:.0f} | {row['p99_ms']:.0f} | {row['refused_503']} |"
    )


def smoke_setup(work: Path) -> tuple[dict[str, Path], list[Path]]:
    """A tiny synthetic model and six generated PNG frames."""
    import cv2
    import torch

    from relocfw import Relocalizer
    from relocfw.model.model_file import save_model
    from relocfw.plugins.exhaustive_index import ExhaustiveIndex
    from relocfw.plugins.posenet import PoseNet
    from relocfw.plugins.sweep_crop import SweepCrop

    torch.manual_seed(0)
    backbone = PoseNet(input_size=32, width=0.125, feature_dim=32)
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), SweepCrop())
    relocalizer.fit([np.zeros((36, 48, 3), np.uint8), np.full((36, 48, 3), 200, np.uint8)])
    parts = {"backbone": {"input_size": 32, "width": 0.125, "feature_dim": 32}}
    model = save_model(work / "tiny.relocfw", relocalizer, parts, {"dataset": "synthetic"})
    folder = work / "smoke-frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    frames = []
    for index in range(6):
        path = folder / f"frame-{index:06d}.color.png"
        cv2.imwrite(str(path), rng.integers(0, 256, (36, 48, 3), dtype=np.uint8))
        frames.append(path)
    return {"tiny": model}, frames


def parse_models(values: list[str]) -> dict[str, Path]:
    models = {}
    for value in values:
        name, _, path = value.rpartition("=")
        models[name or Path(path).stem] = Path(path)
    return models


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", action="append", default=[], help="NAME=MODEL_FILE")
    parser.add_argument("--frames", help="a glob of the query frames (sorted)")
    parser.add_argument("--limit", type=int, default=64, help="the first N frames")
    parser.add_argument("--clients", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--queries", type=int, default=16, help="queries per client")
    parser.add_argument(
        "--slow-clients",
        type=int,
        default=8,
        help="silent slow clients held open in one more row (the most --clients); 0: none",
    )
    parser.add_argument(
        "--override", action="append", default=[], help="key=value for localize and serve"
    )
    parser.add_argument(
        "--serve-override", action="append", default=[], help="key=value for serve only"
    )
    parser.add_argument("--smoke", action="store_true", help="a tiny model, seconds")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/serve_load.json"))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as temporary:
        work = Path(temporary)
        if args.smoke:
            models, frames = smoke_setup(work)
            args.override = [*args.override, "engine=torch"]
        else:
            if not args.model or not args.frames:
                parser.error("give --model NAME=FILE (one or more) and --frames GLOB, or --smoke")
            models = parse_models(args.model)
            frames = [Path(p) for p in sorted(glob.glob(args.frames))][: args.limit]
            if not frames:
                parser.error(f"--frames {args.frames}: no files")
        rows, settings = [], {}
        for name, model in models.items():
            model_rows, settings[name] = measure_model(name, model, frames, args, work)
            rows += model_rows
    report = {
        "command": " ".join(sys.argv),
        "smoke": args.smoke,
        "frames": len(frames),
        "queries_per_client": args.queries,
        "slow_clients": args.slow_clients,
        "cpu_cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "machine": platform.platform(),
        "models": settings,
        "rows": rows,
    }
    from relocfw.core.atomic_files import write_text_atomic

    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(json.dumps(report, indent=2) + "\n", args.out)
    print(TABLE_HEAD)
    for row in rows:
        print(table_line(row))
    print(f"written: {args.out}")


if __name__ == "__main__":
    main()
