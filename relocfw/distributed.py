"""Training across processes: which share of each batch is ours, and agreeing on numbers.

Data parallel training keeps every process on the same batch order: all of them draw
the same global batch (indices and crop offsets) from the same seeded generator and
each takes every `size`-th image from `rank` on. That is a distributed sampler with
no state of its own to save, so a resumed run continues the same stream as before.
DistributedDataParallel averages gradients, so one step equals one step of a single
process on the whole global batch (up to batch normalisation, whose statistics stay
per process on CPU: torch's SyncBatchNorm needs a GPU).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.distributed as dist

from relocfw.errors import ConfigError


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

    def barrier(self) -> None:
        dist.barrier()
