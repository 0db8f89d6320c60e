"""`relocfw`: the Hydra command line. Each `task=` runs one module's `run` (TASKS);
the config's types are relocfw.app.config_schema, old spellings relocfw.app.spellings."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

import hydra
import torch
from omegaconf import DictConfig

from relocfw.app import spellings
from relocfw.app.config_schema import name_of, store
from relocfw.app.engines import check_common
from relocfw.app.hydra_errors import COMPOSITION_ERRORS, one_line
from relocfw.app.hydra_plugins import install as install_plugin_discovery
from relocfw.app.plugin_discovery import conflicts, discover_options
from relocfw.app.tasks import (
    compare,
    diagnose,
    export,
    localize,
    plugins,
    relocalize,
    serve,
    topics,
    train,
)
from relocfw.app.torchrun import join_torchrun, leave_torchrun
from relocfw.core.errors import ConfigError, RelocfwError
from relocfw.model.distributed import World

TaskRun = Callable[[DictConfig, torch.device, World | None], None]
# Every choice of `task` (relocfw.app.config_schema.Task) and what runs it.
TASKS: dict[str, TaskRun] = {
    "relocalize": relocalize.run,
    "train": train.run,
    "compare": compare.run,
    "localize": localize.run,
    "plugins": plugins.run,
    "diagnose": diagnose.run,
    "export": export.run,
    "serve": serve.run,
    "topics": topics.run,
}
FULL_ERROR = "HYDRA_FULL_ERROR"  # Hydra's own switch: raise instead of printing


def run(cfg: DictConfig) -> None:
    device = check_common(cfg)
    task = name_of(cfg.task)
    world, device = join_torchrun(task, device)
    try:
        TASKS[task](cfg, device, world)
    finally:
        leave_torchrun(world)


@hydra.main(version_base="1.3", config_path="pkg://relocfw.conf", config_name="config")
def hydra_main(cfg: DictConfig) -> None:
    try:
        run(cfg)
    except RelocfwError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)


def respell_command_line() -> None:
    """Read old spellings (`scoring=shared`) as their new keys, one note per key; a
    removed option (`query.retrieval_k`) ends in one line giving its new spelling."""
    try:
        arguments, found = spellings.rewrite(sys.argv[1:])
    except ConfigError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)
    for rewrite in found:
        print(rewrite.note(), file=sys.stderr)
    sys.argv[1:] = arguments


def main() -> None:
    """Console-script entry point.

    A config Hydra refuses (a wrong type, an unknown choice or option) ends in one line
    and exit status 2, as relocfw's own errors do; HYDRA_FULL_ERROR=1 shows Hydra's
    full report instead. Ctrl-C ends it with one line and exit status 130 (128 +
    SIGINT, as a shell reports it), not a traceback.
    """
    report_in_one_line = os.environ.get(FULL_ERROR) != "1"
    try:
        store()
        install_plugin_discovery()
        for line in conflicts(discover_options()):
            print(f"warning: {line}", file=sys.stderr)
        respell_command_line()
        if report_in_one_line:
            os.environ[FULL_ERROR] = "1"  # Hydra raises, and the line is written here
        hydra_main()
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
    except COMPOSITION_ERRORS as error:
        if not report_in_one_line:
            raise
        print(f"error: {one_line(error)}", file=sys.stderr)
        sys.exit(2)
    finally:
        if report_in_one_line:
            os.environ.pop(FULL_ERROR, None)


if __name__ == "__main__":
    main()
