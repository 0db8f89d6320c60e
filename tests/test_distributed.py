"""Data-parallel training: two gloo processes on loopback against one process."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch.distributed as dist

from tests.conftest import TINY_OVERRIDES

WORKER = Path(__file__).with_name("ddp_worker.py")
REPO = Path(__file__).resolve().parents[1]

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


def test_two_processes_train_as_one_on_the_whole_batch(tmp_path):
    single, double = tmp_path / "single", tmp_path / "double"
    single.mkdir()
    double.mkdir()
    environment = {**os.environ, "PYTHONPATH": str(REPO)}
    subprocess.run([sys.executable, str(WORKER), str(single)], check=True, env=environment)
    result = torchrun(str(WORKER), str(double), cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    one = json.loads((single / "losses-rank0.json").read_text())
    assert one["batch_sizes"] == [8] * 6
    for rank in (0, 1):
        two = json.loads((double / f"losses-rank{rank}.json").read_text())
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


def test_torchrun_trains_through_the_cli_and_refuses_other_tasks(tmp_path):
    env = {"RELOCFW_CACHE": str(tmp_path / "cache")}
    result = torchrun("-m", "relocfw", "task=train", *TINY_OVERRIDES, cwd=tmp_path, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.count("model:") == 1  # printed by rank 0 only
    assert len(list((tmp_path / "cache" / "checkpoints").glob("*.pt"))) == 1
    refused = torchrun("-m", "relocfw", *TINY_OVERRIDES, cwd=tmp_path, env=env)
    assert refused.returncode != 0
    assert "under torchrun (2 processes) only task=train runs" in refused.stderr
