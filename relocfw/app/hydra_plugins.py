"""Hydra's side of plugin discovery: every plugin's config package joins the search path."""

from __future__ import annotations

from hydra.core.config_search_path import ConfigSearchPath
from hydra.core.plugins import Plugins
from hydra.plugins.search_path_plugin import SearchPathPlugin
from omegaconf import OmegaConf

from relocfw.app.plugin_discovery import (
    config_sources,
    conflicts,
    describe_options,
    discover_options,
    package_folder,
)


class RelocfwPluginSearchPath(SearchPathPlugin):
    """Appends each `relocfw.configs` entry point's config folder as `file://`.

    Not `pkg://<package>`: Hydra imports a pkg:// package (running the plugin's
    __init__), so one plugin that raises on import would break every run.
    """

    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        for source in config_sources()[1:]:
            folder = package_folder(source.package)
            if folder is not None:
                search_path.append(provider=source.distribution, path=f"file://{folder}")


def options_help() -> str:
    options = discover_options()
    text = describe_options(options)
    clashes = conflicts(options)
    if clashes:
        text += "\n\nconflicts:\n" + "\n".join(f"  {line}" for line in clashes)
    return text


def install() -> None:
    """Register the search path plugin and the `${relocfw_options:}` help resolver."""
    Plugins.instance().register(RelocfwPluginSearchPath)
    OmegaConf.register_new_resolver("relocfw_options", options_help, replace=True)
