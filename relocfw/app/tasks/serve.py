"""task=serve: the model file as an HTTP service (relocfw.serve; docs/serve.md).

`relocfw task=serve serve.model=MODEL` loads the model as task=localize does (its
query options, each query.* value that is set replacing the file's, the configured
engine) and answers POST /v1/localize until SIGTERM. FastAPI and uvicorn come with
`pip install "relocfw[serve]"`.

`relocfw-serve MODEL [key=value ...]` (`main`; also `python -m relocfw.app.tasks.serve`)
is the same command without task=: it composes the config itself.
"""

from __future__ import annotations

import functools
import sys
from types import ModuleType
from typing import Any

import torch
from hydra import compose, initialize_config_module
from omegaconf import DictConfig, OmegaConf

from relocfw.app.config_schema import store
from relocfw.app.engines import check_common, on_engine
from relocfw.app.hydra_errors import COMPOSITION_ERRORS, one_line
from relocfw.app.hydra_plugins import install as install_plugin_discovery
from relocfw.app.methods import in_query_terms, query_values
from relocfw.app.tasks.localize import model_file
from relocfw.core.errors import ConfigError, RelocfwError
from relocfw.core.pipeline import Relocalizer
from relocfw.model.distributed import World
from relocfw.model.model_file import load_model
from relocfw.serve.settings import ServeSettings

USAGE = """usage: relocfw-serve MODEL [key=value ...]

Serve a model file over HTTP (docs/serve.md): POST /v1/localize, GET /v1/health,
GET /v1/model. The same as `relocfw task=serve serve.model=MODEL ...`; keys such as
serve.port=8000 serve.host=0.0.0.0 serve.workers=2 serve.token_file=FILE engine=torch.
"""
INSTALL_HINT = 'task=serve needs FastAPI and uvicorn: pip install "relocfw[serve]"'


def service_module() -> ModuleType:
    """relocfw.serve.service, or a ConfigError saying how to install what it needs."""
    try:
        from relocfw.serve import service
    except ModuleNotFoundError as error:
        if (error.name or "").split(".")[0] in ("fastapi", "uvicorn", "starlette"):
            raise ConfigError(INSTALL_HINT) from None
        raise
    return service


def load_for_serve(config: dict[str, Any], device: str) -> Relocalizer:
    """The model of serve.model, as task=localize loads localize.model. Takes the config
    as plain values so a worker process can be given it (serve.workers > 1)."""
    cfg = OmegaConf.create(config)
    model = model_file(cfg.serve.model, "serve.model")
    where = torch.device(device)
    try:
        relocalizer = load_model(model, where, query_values(cfg))
    except ConfigError as error:
        raise in_query_terms(error) from error
    return on_engine(cfg, relocalizer, model, where)


def run(cfg: DictConfig, device: torch.device, world: World | None) -> None:
    settings = ServeSettings.from_config(cfg.serve)
    service = service_module()
    service.check_open_files(settings)  # before the model's seconds of loading
    config = OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
    loader = functools.partial(load_for_serve, config, str(device))
    service.run_service(settings, loader(), loader)


def main(arguments: list[str] | None = None) -> None:
    """Console-script entry point; errors end in one line and exit status 2."""
    given = sys.argv[1:] if arguments is None else arguments
    if not given or given[0] in ("-h", "--help") or "=" in given[0]:
        print(USAGE, file=sys.stderr if not given or "=" in given[0] else sys.stdout)
        sys.exit(0 if given and given[0] in ("-h", "--help") else 2)
    overrides = ["task=serve", f"serve.model={given[0]}", *given[1:]]
    try:
        store()
        install_plugin_discovery()
        with initialize_config_module(config_module="relocfw.conf", version_base="1.3"):
            cfg = compose("config", overrides=overrides)
        run(cfg, check_common(cfg), None)
    except RelocfwError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)
    except COMPOSITION_ERRORS as error:
        print(f"error: {one_line(error)}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        # Ctrl-C before the service was up (while loading): nothing was served. Once
        # it serves, Ctrl-C drains as SIGTERM does and exits 0 (relocfw.serve.service).
        print("interrupted", file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()
