"""Shared fixtures: tiny scenes and networks, so each test file runs in seconds."""

from __future__ import annotations

import os
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


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every test under tests/app/ runs the CLI end to end: mark it slow."""
    for item in items:
        if APP_TESTS in Path(item.fspath).parents:
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
