"""Shared fixtures: tiny scenes and networks, so each test file runs in seconds."""

from __future__ import annotations

import inspect
import os
import re
from pathlib import Path

import pytest

SAMPLE_ROOT = Path(__file__).resolve().parents[2] / "shared" / "data" / "7scenes-stairs-sample"

# Overrides that shrink the CLI job to a few seconds: a 48x36 scene, 32-pixel input,
# a GoogLeNet at 1/8 width, three training steps.
TINY_MODEL = [
    "backbone.input_size=32",
    "backbone.width=0.125",
    "backbone.feature_dim=64",
    "train.iterations=3",
    "train.batch_size=4",
    "k=4",
    "quiet=true",
    "hydra.job_logging.root.level=WARNING",
]
TINY_SCENE = [
    "dataset.width=48",
    "dataset.height=36",
    "dataset.train_laps=2",
    "dataset.train_frames_per_lap=8",
    "dataset.test_frames=4",
]
TINY_OVERRIDES = TINY_MODEL + TINY_SCENE


APP_TESTS = Path(__file__).parent / "app"


def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist (`-n N`), share the cores among the workers: each worker's
    torch, and the relocfw processes it starts, get cores / N threads. N workers with
    a full OpenMP team each would spin on the same cores."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers is None:
        return
    import torch

    threads = max(1, (os.cpu_count() or 1) // int(workers))
    torch.set_num_threads(threads)
    os.environ["OMP_NUM_THREADS"] = str(threads)


# What a test or fixture that starts a process of its own says in its source: the CLI
# through tests.cli_runs.relocfw, pip, torchrun, a benchmark script.
STARTS_A_PROCESS = re.compile(r"\brelocfw\(|\bsubprocess\.|\bPopen\(|\brun_script\(")


def source_of(function: object) -> str:
    try:
        return inspect.getsource(function)
    except (OSError, TypeError):
        return ""


def starts_a_process(item: pytest.Item) -> bool:
    """Whether the test, a fixture it uses, or a function of its module that either
    calls, starts a process (read from the source, one call deep)."""
    functions = [getattr(item, "function", None)]
    fixtures = getattr(item, "_fixtureinfo", None)
    if fixtures is not None:
        functions += [d.func for defs in fixtures.name2fixturedefs.values() for d in defs]
    module = getattr(item, "module", None)
    helpers = (
        {
            name: value
            for name, value in vars(module).items()
            if inspect.isfunction(value) and value.__module__ == module.__name__
        }
        if module is not None
        else {}
    )
    for function in functions:
        source = source_of(function)
        called = [h for name, h in helpers.items() if re.search(rf"\b{name}\(", source)]
        if any(STARTS_A_PROCESS.search(text) for text in [source, *map(source_of, called)]):
            return True
    return False


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every test under tests/app/ runs the CLI end to end, and every other test that
    starts a process (directly or through a fixture) pays seconds for it: mark them
    slow, so `pytest -m "not slow"` is the inner loop."""
    for item in items:
        if APP_TESTS in Path(item.fspath).parents or starts_a_process(item):
            item.add_marker(pytest.mark.slow)


@pytest.fixture
def stairs_sample() -> Path:
    """The real 7-Scenes Stairs frames in ../shared (never copied into the repo)."""
    if not (SAMPLE_ROOT / "stairs" / "TrainSplit.txt").is_file():
        pytest.skip(f"7-Scenes sample not found at {SAMPLE_ROOT}")
    return SAMPLE_ROOT


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A rendered 48x36 synthetic scene in the 7-Scenes layout."""
    from relocfw.data.synthetic import SyntheticSceneSpec, ensure_synthetic_scene

    spec = SyntheticSceneSpec(
        width=48, height=36, train_laps=2, train_frames_per_lap=8, test_frames=4
    )
    return ensure_synthetic_scene(spec, tmp_path_factory.mktemp("cache"), quiet=True)
