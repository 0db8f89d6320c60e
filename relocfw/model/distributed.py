"""Training across processes: which share of each batch is ours, and agreeing on numbers.

Data parallel training keeps every process on the same batch order: all of them draw
the same global batch (indices and crop offsets) from the same seeded generator and
each takes every `size`-th image from `rank` on. That is a distributed sampler with
no state of its own to save, so a resumed run continues the same stream as before.
DistributedDataParallel averages gradients, so one step equals one step of a single
process on the whole global batch, up to two things that are meant to differ:

- Dropout: each process seeds torch's own streams from (seed, rank), so the processes
  draw different dropout masks, as one process on the whole batch would draw a
  different mask for every image. Checkpoints keep every process's stream (CPU, and
  the process's GPU when training on CUDA), and a resumed run gives each its own back.
- Batch normalisation: on CUDA the backbone's batch-norm layers become SyncBatchNorm,
  so statistics are taken over the global batch. On CPU (gloo) they stay per process,
  over each process's share: torch's SyncBatchNorm runs on GPUs only.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist

from relocfw.core.errors import ConfigError, DataError

# One process's random streams as saved in a checkpoint: "cpu", and "cuda" on a GPU.
RngState = dict[str, torch.Tensor]


@dataclass(frozen=True)
class World:
    """This process's place among `size` training processes (torch.distributed)."""

    rank: int
    size: int

    @classmethod
    def current(cls) -> World:
        """The initialised default process group's rank and size."""
        if not (dist.is_available() and dist.is_initialized()):
            raise ConfigError("distributed training needs torch.distributed initialised")
        return cls(dist.get_rank(), dist.get_world_size())

    @property
    def is_main(self) -> bool:
        """Rank 0 writes checkpoints and prints; the others stay quiet."""
        return self.rank == 0

    def check_batch(self, batch_size: int) -> None:
        if batch_size % self.size:
            raise ConfigError(
                f"train.batch_size={batch_size} does not split evenly over {self.size} "
                f"processes; use a multiple of {self.size}"
            )

    def torch_seed(self, seed: int) -> int:
        """This process's seed for torch's own streams (dropout), derived from (seed, rank).

        Hashed rather than `seed + rank`, so that runs with neighbouring seeds do not
        share streams between their ranks.
        """
        digest = hashlib.sha256(f"relocfw process seed {seed} {self.rank}".encode()).digest()
        # 63 bits: inside the range torch.manual_seed accepts.
        return int.from_bytes(digest[:8], "little") >> 1

    def share(self, tensor: torch.Tensor) -> torch.Tensor:
        """This process's rows of a global batch."""
        return tensor[self.rank :: self.size]

    def mean(self, value: torch.Tensor) -> torch.Tensor:
        """The mean of a scalar over all processes (every process gets it)."""
        total = value.detach().clone()
        dist.all_reduce(total)
        return total / self.size

    def average_gradients(self, module: torch.nn.Module) -> None:
        """Average gradients of a module outside DistributedDataParallel (e.g. the loss's)."""
        for parameter in module.parameters():
            if parameter.grad is not None:
                dist.all_reduce(parameter.grad)
                parameter.grad /= self.size

    def gather(self, value: Any) -> list[Any] | None:
        """Every process's `value` in rank order on rank 0, None on the others.

        A collective: every process must call it at the same point.
        """
        values: list[Any] | None = [None] * self.size if self.is_main else None
        dist.gather_object(value, values, dst=0)
        return values

    def barrier(self) -> None:
        dist.barrier()


def synchronise_batch_norm(module: torch.nn.Module, device: torch.device) -> torch.nn.Module:
    """`module` with its batch-norm layers as SyncBatchNorm when training on CUDA.

    The layers are replaced in place and keep their parameters and buffers (the same
    tensors, under the same state_dict keys), so checkpoints still load into an
    ordinary backbone; in eval mode SyncBatchNorm is plain batch norm. Elsewhere the
    module is returned unchanged: SyncBatchNorm refuses CPU tensors in training.
    """
    if device.type != "cuda":
        return module
    return torch.nn.SyncBatchNorm.convert_sync_batchnorm(module)


def data_parallel(
    backbone: torch.nn.Module, world: World | None, device: torch.device
) -> torch.nn.Module:
    """The module to train: `backbone` itself, or under a world its DDP wrapper.

    DistributedDataParallel broadcasts rank 0's initial weights and averages gradients
    in backward; batch norm is synchronised first where torch can (CUDA).
    """
    if world is None:
        return backbone
    synchronised = synchronise_batch_norm(backbone, device)
    device_ids = [device.index] if device.type == "cuda" else None
    return torch.nn.parallel.DistributedDataParallel(synchronised, device_ids=device_ids)


def rng_state(device: torch.device) -> RngState:
    """This process's torch random streams: the CPU one and, on CUDA, `device`'s."""
    state = {"cpu": torch.get_rng_state()}
    if device.type == "cuda":
        # Dropout on a GPU draws from the device's own generator, not the CPU one.
        state["cuda"] = torch.cuda.get_rng_state(device)
    return state


def restore_rng_state(state: RngState, device: torch.device) -> None:
    """Put back what `rng_state` saved.

    A CUDA stream is restored when training on CUDA again; a run resumed on another
    kind of device keeps its freshly seeded GPU stream (its masks differ anyway).
    """
    torch.set_rng_state(state["cpu"])
    if device.type == "cuda" and "cuda" in state:
        torch.cuda.set_rng_state(state["cuda"], device)


def gather_rng_states(world: World | None, device: torch.device) -> list[RngState] | None:
    """Every process's `rng_state` in rank order where checkpoints are written.

    A list of one without a world; under one, rank 0 gets the list and the others
    None. Every process must call it at the same point (a collective).
    """
    state = rng_state(device)
    return [state] if world is None else world.gather(state)


def restore_own_rng_state(
    states: Sequence[RngState],
    world: World | None,
    device: torch.device,
    checkpoint: Path | str,
) -> None:
    """Give this process back its own stream from a checkpoint's per-rank list.

    A checkpoint is resumed only by as many processes as wrote it: with another
    number the per-process dropout streams and the batch shares no longer match the
    interrupted run, so it could not continue as it would have; say so instead.
    """
    size = 1 if world is None else world.size
    if len(states) != size:
        how = "without torchrun" if len(states) == 1 else f"torchrun --nproc-per-node={len(states)}"
        raise DataError(
            f"{checkpoint} is an interrupted run of {len(states)} training process(es); "
            f"this run has {size}. Resume it with as many ({how}), or delete it to train "
            "afresh"
        )
    restore_rng_state(states[0 if world is None else world.rank], device)
