"""Data-parallel training: two gloo processes on loopback against one process."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch.distributed as dist

from relocfw.core.errors import DataError
from relocfw.model.training import train_backbone
from tests.conftest import TINY_OVERRIDES
from tests.model.ddp_worker import DROPOUT, TinyConvPose, training_data

WORKER = Path(__file__).with_name("ddp_worker.py")
REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(
    not dist.is_available() or not dist.is_gloo_available(), reason="torch without gloo"
)


def torchrun(*args: str, cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone"]
    command += ["--nproc-per-node=2", *args]
    environment = {**os.environ, "PYTHONPATH": str(REPO), **(env or {})}
    return subprocess.run(
        command, cwd=cwd, env=environment, capture_output=True, text=True, timeout=300
    )


@pytest.fixture(scope="module")
def worker_runs(tmp_path_factory) -> tuple[Path, Path]:
    """The worker's scenarios in one process and in two (each start costs seconds)."""
    single = tmp_path_factory.mktemp("single")
    double = tmp_path_factory.mktemp("double")
    environment = {**os.environ, "PYTHONPATH": str(REPO)}
    subprocess.run([sys.executable, str(WORKER), str(single)], check=True, env=environment)
    result = torchrun(str(WORKER), str(double), cwd=double)
    assert result.returncode == 0, result.stderr[-3000:]
    return single, double


def read(folder: Path, name: str) -> dict:
    return json.loads((folder / name).read_text())


def test_two_processes_train_as_one_on_the_whole_batch(worker_runs):
    single, double = (folder / "plain" for folder in worker_runs)
    one = read(single, "losses-rank0.json")
    assert one["batch_sizes"] == [8] * 6
    for rank in (0, 1):
        two = read(double, f"losses-rank{rank}.json")
        assert len(two["losses"]) == 6
        assert two["batch_sizes"] == [4] * 6  # each process saw its half of every batch
        assert np.allclose(two["losses"], one["losses"], rtol=1e-5, atol=1e-6)
        assert np.allclose(two["weights"], one["weights"], rtol=1e-4, atol=1e-6)
    moved = np.abs(np.subtract(one["weights"], one["initial"])).max()
    assert moved > 1e-3  # the steps did change the weights, so equality means something
    # Rank 0 alone wrote the checkpoint; no other files, no temporaries.
    assert sorted(p.name for p in double.iterdir()) == [
        "losses-rank0.json",
        "losses-rank1.json",
        "model.pt",
    ]


def test_ranks_draw_their_own_dropout_masks_on_one_global_batch(worker_runs):
    single, double = (folder / "dropout" for folder in worker_runs)
    one = read(single, "dropout-rank0.json")
    ranks = [read(double, f"dropout-rank{rank}.json") for rank in (0, 1)]
    for step, rows in enumerate(one["rows"]):
        # Both processes drew the same global batch and took alternate images of it.
        for rank, two in enumerate(ranks):
            assert np.allclose(two["rows"][step], rows[rank::2], rtol=1e-6), (step, rank)
    masks = [np.array(two["masks"]) for two in ranks]
    assert masks[0].shape == masks[1].shape == (6, 4, 8)
    assert 0.2 < masks[0].mean() < 0.8  # dropout did drop some units, not all
    differing = [step for step in range(6) if (masks[0][step] != masks[1][step]).any()]
    assert differing == list(range(6)), "the two processes drew identical dropout masks"


def test_a_resumed_two_process_run_continues_every_ranks_stream(worker_runs):
    double = worker_runs[1] / "dropout"
    ranks = [read(double, f"dropout-rank{rank}.json") for rank in (0, 1)]
    # The resumed steps drew the masks the uninterrupted run drew on the same rank ...
    assert [two["resumed_from"] for two in ranks] == [4, 4]
    same = [two["resumed_masks"] == two["masks"][4:] for two in ranks]
    assert same == [True, True], "the ranks resumed with other dropout masks"
    # ... so the run ends where the uninterrupted one did (losses are global means).
    for two in ranks:
        assert np.allclose(two["resumed_losses"], two["losses"], rtol=1e-6, atol=1e-7)
        assert np.allclose(two["resumed_weights"], two["weights"], rtol=1e-6, atol=1e-7)


def test_a_two_process_checkpoint_is_not_resumed_by_one_process(worker_runs, tmp_path):
    checkpoint = tmp_path / "run.pt"
    shutil.copy(worker_runs[1] / "dropout" / "interrupted.pt", checkpoint)
    with pytest.raises(DataError, match=r"interrupted run of 2 training process\(es\)"):
        train_backbone(TinyConvPose(0.5), training_data(), DROPOUT, checkpoint, "tiny", quiet=True)


def test_torchrun_trains_through_the_cli_and_refuses_other_tasks(tmp_path):
    env = {"RELOCFW_CACHE": str(tmp_path / "cache")}
    result = torchrun("-m", "relocfw", "task=train", *TINY_OVERRIDES, cwd=tmp_path, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.count("model:") == 1  # printed by rank 0 only
    assert len(list((tmp_path / "cache" / "checkpoints").glob("*.pt"))) == 1
    refused = torchrun("-m", "relocfw", *TINY_OVERRIDES, cwd=tmp_path, env=env)
    assert refused.returncode != 0
    assert "under torchrun (2 processes) only task=train runs" in refused.stderr
