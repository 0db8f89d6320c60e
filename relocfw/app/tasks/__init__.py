"""One module per task, each with one entry function of the same signature:

    run(cfg: DictConfig, device: torch.device, world: World | None) -> None

`cfg` is the composed config, `device` the checked device (`device=`), `world` the
torchrun process group (None in one process; only task=train runs under torchrun).
relocfw.app.cli maps each `task=` choice to its module's `run`.
"""
