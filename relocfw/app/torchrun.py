"""Joining the process group torchrun sets up; the CLI's side of distributed training.

    torchrun --nproc-per-node=2 -m relocfw task=train [options]

torchrun starts the processes and sets WORLD_SIZE, RANK and LOCAL_RANK; each one runs
the CLI, which joins the group here: gloo on CPU, nccl with one GPU per process. On
GPUs batch norm is synchronised over the processes, on CPU it stays per process
(relocfw.model.distributed says why); either way each process draws its own dropout masks.
"""

from __future__ import annotations

import os

import torch
import torch.distributed as dist

from relocfw.core.errors import ConfigError
from relocfw.model.distributed import World


def join_torchrun(task: str, device: torch.device) -> tuple[World | None, torch.device]:
    """The World of this process and its device, or (None, device) when not under torchrun."""
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1:
        return None, device
    if task != "train":
        raise ConfigError(
            f"under torchrun ({size} processes) only task=train runs; run task={task} "
            "afterwards in one process: it reuses the trained checkpoint"
        )
    backend = "gloo"
    if device.type == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
        backend = "nccl"
    dist.init_process_group(backend)
    return World.current(), device


def leave_torchrun(world: World | None) -> None:
    if world is not None and dist.is_initialized():
        dist.destroy_process_group()
