"""Which config options exist and where they come from, without importing plugin code.

A third-party package publishes a config package through the entry point group
`relocfw.configs` (e.g. `mycrop = "relocfw_mycrop.conf"`); the package holds group
folders (crop/, index/, backbone/, dataset/) of YAML files. Discovery reads entry
point metadata and lists YAML files: no plugin module is imported, so a broken
plugin can only fail when it is chosen.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path

# The Hydra-free part lives in core, where the model loader can use it too; the names
# stay importable from here.
from relocfw.core.plugin_registry import (
    BUILTIN_PACKAGE,
    ENTRY_POINT_GROUP,
    ConfigSource,
    config_sources,
    package_folder,
)

__all__ = [
    "BUILTIN_PACKAGE",
    "ENTRY_POINT_GROUP",
    "GROUPS",
    "ConfigSource",
    "Option",
    "config_sources",
    "conflicts",
    "describe_options",
    "discover_options",
    "first_comment",
    "package_folder",
    "source_of",
]

GROUPS = {
    "backbone": "Backbone",
    "index": "SimilarityIndex",
    "crop": "CropSearch",
    "refine": "PoseRefiner",
    "dataset": "dataset",
    "preset": "settings preset",
}


@dataclass(frozen=True)
class Option:
    group: str
    name: str
    source: ConfigSource
    description: str  # the YAML's first comment line


def first_comment(path: Path) -> str:
    for line in path.read_text().splitlines():
        text = line.strip()
        if text.startswith("# @package"):
            continue
        if text.startswith("#"):
            return text.lstrip("#").strip()
        if text:
            break
    return ""


@cache
def discover_options() -> tuple[Option, ...]:
    """Every option of every group, in search-path order (first one wins).

    Cached: installed packages do not change while relocfw runs, and the CLI asks
    for every plugin it builds.
    """
    options = []
    for source in config_sources():
        folder = package_folder(source.package)
        if folder is None:
            continue
        for group in GROUPS:
            for path in sorted((folder / group).glob("*.yaml")):
                options.append(Option(group, path.stem, source, first_comment(path)))
    return tuple(options)


def conflicts(options: Sequence[Option]) -> list[str]:
    """One line for each option name offered by more than one package."""
    seen: dict[tuple[str, str], Option] = {}
    lines = []
    for option in options:
        key = (option.group, option.name)
        if key in seen:
            first = seen[key]
            lines.append(
                f"{option.group}={option.name} is offered by {first.source.distribution} "
                f"and {option.source.distribution}; {first.source.distribution}'s is used"
            )
        else:
            seen[key] = option
    return lines


def describe_options(options: Sequence[Option]) -> str:
    """A listing by group: option, package, interface and description."""
    lines = []
    for group, interface in GROUPS.items():
        lines.append(f"{group} ({interface}):")
        for option in [o for o in options if o.group == group]:
            origin = option.source.distribution
            lines.append(f"  {option.name:<22} [{origin}] {option.description}")
    return "\n".join(lines)


def source_of(group: str, name: str) -> ConfigSource | None:
    for option in discover_options():
        if option.group == group and option.name == name:
            return option.source
    return None
