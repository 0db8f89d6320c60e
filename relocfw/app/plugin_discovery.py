"""Which config options exist and where they come from, without importing plugin code.

A third-party package publishes a config package through the entry point group
`relocfw.configs` (e.g. `mycrop = "relocfw_mycrop.conf"`); the package holds group
folders (crop/, index/, backbone/, dataset/) of YAML files. Discovery reads entry
point metadata and lists YAML files: no plugin module is imported, so a broken
plugin can only fail when it is chosen.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from importlib import metadata
from importlib.resources import files
from pathlib import Path

ENTRY_POINT_GROUP = "relocfw.configs"
BUILTIN_PACKAGE = "relocfw.conf"
GROUPS = {
    "backbone": "Backbone",
    "index": "SimilarityIndex",
    "crop": "CropSearch",
    "dataset": "dataset",
    "preset": "settings preset",
}


@dataclass(frozen=True)
class ConfigSource:
    """A config package and the distribution that ships it."""

    package: str  # importable name, e.g. "relocfw_mycrop.conf"
    distribution: str  # e.g. "relocfw-mycrop", or "relocfw" for the built-ins


@dataclass(frozen=True)
class Option:
    group: str
    name: str
    source: ConfigSource
    description: str  # the YAML's first comment line


def config_sources() -> list[ConfigSource]:
    """The built-in config package, then every installed plugin's, sorted by name."""
    sources = [ConfigSource(BUILTIN_PACKAGE, "relocfw")]
    found = []
    for entry in metadata.entry_points(group=ENTRY_POINT_GROUP):
        distribution = entry.dist.name if entry.dist is not None else entry.name
        found.append(ConfigSource(entry.value, distribution))
    return sources + sorted(set(found), key=lambda s: (s.distribution, s.package))


def package_folder(package: str) -> Path | None:
    """Where a package's files are, found without running its __init__."""
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    if package == BUILTIN_PACKAGE:
        return Path(str(files(package)))
    return Path(next(iter(spec.submodule_search_locations)))


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
