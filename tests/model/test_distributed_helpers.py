"""The single-process side of data-parallel training: seeds, random streams, batch norm.

No process group is needed here (tests/model/test_distributed.py runs real ones), nor a GPU:
converting to SyncBatchNorm builds modules only, and the CUDA stream calls are stubbed.
"""

import pytest
import torch
from torch import nn

from relocfw.core.errors import DataError
from relocfw.model.checkpoints import load_checkpoint
from relocfw.model.distributed import (
    World,
    data_parallel,
    gather_rng_states,
    restore_own_rng_state,
    restore_rng_state,
    rng_state,
    synchronise_batch_norm,
)
from relocfw.model.training import TrainSettings, train_backbone
from tests.model.ddp_worker import TinyConvPose, training_data

CPU, CUDA = torch.device("cpu"), torch.device("cuda", 1)


def batch_norm_net() -> nn.Module:
    torch.manual_seed(0)
    return nn.Sequential(
        nn.Conv2d(3, 4, 3),
        nn.BatchNorm2d(4),
        nn.ReLU(),
        nn.Sequential(nn.Conv2d(4, 4, 1), nn.BatchNorm2d(4, momentum=0.3)),
    )


def test_batch_norm_becomes_synchronised_for_cuda_with_the_same_state():
    net = batch_norm_net()
    net(torch.rand(2, 3, 6, 6))  # training-mode statistics, so the buffers are not defaults
    before = {key: value.clone() for key, value in net.state_dict().items()}
    converted = synchronise_batch_norm(net, torch.device("cuda"))
    norms = [m for m in converted.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    assert len(norms) == 2
    assert all(type(m) is nn.SyncBatchNorm for m in norms), [type(m) for m in norms]
    assert norms[1].momentum == 0.3
    state = converted.state_dict()
    assert list(state) == list(before)  # checkpoints keep their keys
    assert all(torch.equal(state[key], before[key]) for key in before)
    ordinary = batch_norm_net()
    ordinary.load_state_dict(state)  # strict: loads into a backbone without SyncBatchNorm
    images = torch.rand(2, 3, 6, 6)
    # In eval mode a converted layer is plain batch norm, on CPU too.
    assert torch.equal(converted.eval()(images), ordinary.eval()(images))


def test_batch_norm_stays_per_process_on_cpu():
    net = batch_norm_net()
    assert synchronise_batch_norm(net, CPU) is net
    assert not any(isinstance(m, nn.SyncBatchNorm) for m in net.modules())
    assert data_parallel(net, None, CPU) is net  # one process: no wrapper at all


def test_each_rank_gets_its_own_torch_seed():
    seeds = [World(rank, 2).torch_seed(3) for rank in (0, 1)]
    assert seeds[0] != seeds[1]
    assert seeds == [World(rank, 2).torch_seed(3) for rank in (0, 1)]  # reproducible
    assert World(0, 2).torch_seed(4) not in seeds
    for seed in seeds:
        torch.manual_seed(seed)  # in torch's range


def test_cpu_stream_round_trip():
    state = rng_state(CPU)
    assert set(state) == {"cpu"}
    drawn = torch.rand(5)
    restore_rng_state(state, CPU)
    assert torch.equal(torch.rand(5), drawn)


def test_cuda_stream_of_this_device_is_saved_and_restored(monkeypatch):
    calls = []
    saved = torch.tensor([7, 8], dtype=torch.uint8)

    def get_rng_state(device):
        calls.append(("get", device))
        return saved.clone()

    def set_rng_state(state, device):
        calls.append(("set", device, state.tolist()))

    monkeypatch.setattr(torch.cuda, "get_rng_state", get_rng_state)
    monkeypatch.setattr(torch.cuda, "set_rng_state", set_rng_state)
    state = rng_state(CUDA)
    assert calls == [("get", CUDA)] and torch.equal(state["cuda"], saved)
    restore_rng_state(state, CUDA)
    assert calls[-1] == ("set", CUDA, [7, 8])
    calls.clear()
    restore_rng_state({"cpu": state["cpu"]}, CUDA)  # saved on CPU: nothing to restore
    restore_rng_state(state, CPU)  # resumed on CPU: the GPU stream is not touched
    assert calls == []


def test_each_process_restores_its_own_stream_and_only_with_as_many_processes():
    states = []
    for seed in (1, 2):
        torch.manual_seed(seed)
        states.append(rng_state(CPU))
    restore_own_rng_state(states, World(1, 2), CPU, "run.pt")
    drawn = torch.rand(3)
    torch.manual_seed(2)
    assert torch.equal(torch.rand(3), drawn)  # rank 1 got the second stream
    torch.manual_seed(1)
    assert not torch.equal(torch.rand(3), drawn)
    with pytest.raises(DataError, match=r"run of 2 training process\(es\); this run has 1"):
        restore_own_rng_state(states, None, CPU, "run.pt")
    with pytest.raises(DataError, match="torchrun --nproc-per-node=2"):
        restore_own_rng_state(states, World(0, 3), CPU, "run.pt")
    with pytest.raises(DataError, match="without torchrun"):
        restore_own_rng_state(states[:1], World(0, 2), CPU, "run.pt")


def test_a_single_process_checkpoint_holds_a_list_of_one_stream(tmp_path):
    assert len(gather_rng_states(None, CPU)) == 1
    checkpoint = tmp_path / "run.pt"
    settings = TrainSettings(iterations=4, batch_size=4, checkpoint_every=2, seed=5)
    train_backbone(TinyConvPose(0.5), training_data(), settings, checkpoint, "k", quiet=True)
    streams = load_checkpoint(checkpoint)["rng"]
    assert len(streams) == 1 and set(streams[0]) == {"cpu"}
