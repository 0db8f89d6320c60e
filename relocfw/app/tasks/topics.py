"""task=topics: a bag's topics (type, count, rate, first / last stamp), to pick the
topics of dataset=rosbag or task=localize: `localize.images=BAG` or `dataset.bag=BAG`."""

from __future__ import annotations

import torch
from omegaconf import DictConfig

from relocfw.core.errors import ConfigError, RelocfwError
from relocfw.data.bag_topics import topic_stats, topics_table
from relocfw.model.distributed import World


def bag_option(cfg: DictConfig) -> tuple[str, str]:
    """The key naming the bag and its value: localize.images, else dataset.bag."""
    images = cfg.localize.get("images")
    if images:
        return "localize.images", str(images)
    bag = cfg.dataset.get("bag")
    if bag:
        return "dataset.bag", str(bag)
    raise ConfigError(
        "task=topics lists a bag's topics: pass localize.images=BAG (or dataset.bag=BAG "
        "with dataset=rosbag)"
    )


def run(cfg: DictConfig, device: torch.device, world: World | None) -> None:
    key, bag = bag_option(cfg)
    try:
        stats = topic_stats(bag)
    except RelocfwError as error:
        raise type(error)(f"{key}={bag}: {error}") from error
    print(topics_table(bag, stats))
