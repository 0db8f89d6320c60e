"""The plugin registry: the config groups of relocfw and of installed plugin packages.

A plugin is registered by a YAML in a group folder (backbone/, index/, crop/, ...) of
the built-in config package or of a package published through the entry point group
`relocfw.configs`; the YAML's `_target_` names the class. Everything here reads
entry point metadata, lists folders and parses YAML text: no plugin module is
imported, so the registry can be consulted before anything a file names is run
(the model loader does so), and a broken plugin fails only when it is chosen.

Hydra-free on purpose: the model loader needs it, and only relocfw.app sees Hydra.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from importlib import metadata
from importlib.resources import files
from pathlib import Path

import yaml

ENTRY_POINT_GROUP = "relocfw.configs"
BUILTIN_PACKAGE = "relocfw.conf"


@dataclass(frozen=True)
class ConfigSource:
    """A config package and the distribution that ships it."""

    package: str  # importable name, e.g. "relocfw_mycrop.conf"
    distribution: str  # e.g. "relocfw-mycrop", or "relocfw" for the built-ins


def config_sources() -> list[ConfigSource]:
    """The built-in config package, then every installed plugin's, sorted by name."""
    sources = [ConfigSource(BUILTIN_PACKAGE, "relocfw")]
    found = []
    for entry in metadata.entry_points(group=ENTRY_POINT_GROUP):
        distribution = entry.dist.name if entry.dist is not None else entry.name
        found.append(ConfigSource(entry.value, distribution))
    return sources + sorted(set(found), key=lambda s: (s.distribution, s.package))


def package_folder(package: str) -> Path | None:
    """Where a package's files are, found without running any of its code.

    Only the top-level name is looked up: `find_spec("pkg.conf")` would import `pkg`
    (running its __init__, which may raise or be slow), while `find_spec("pkg")` only
    locates it. The rest of the dotted name is then a subfolder of one of its
    locations (a namespace package may have several).
    """
    if package == BUILTIN_PACKAGE:
        try:
            return Path(str(files(package)))
        except ModuleNotFoundError:
            return None
    top, *inner = package.split(".")
    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    for location in spec.submodule_search_locations:
        folder = Path(location).joinpath(*inner)
        if folder.is_dir():
            return folder
    return mapped_package_folder(package)


def mapped_package_folder(package: str) -> Path | None:
    """A config package that is not a subfolder of its parent (an editable install
    with its own package-dir mapping): found by its full name, which imports the
    parent, so any failure of the parent's code leaves this one plugin unfound."""
    try:
        spec = importlib.util.find_spec(package)
    except Exception:  # the parent's __init__ is a third party's code
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations)))


def group_files(group: str) -> list[tuple[ConfigSource, Path]]:
    """Every option YAML of `group`, in search-path order, with the package it is from."""
    found = []
    for source in config_sources():
        folder = package_folder(source.package)
        if folder is not None:
            found += [(source, path) for path in sorted((folder / group).glob("*.yaml"))]
    return found


def target_of(path: Path) -> str | None:
    """The `_target_` of one option YAML, or None (no target, or not readable YAML).

    A YAML that cannot be read registers nothing rather than failing: one broken
    plugin must not stop every other one from being found.
    """
    try:
        content = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return None
    target = content.get("_target_") if isinstance(content, dict) else None
    return target if isinstance(target, str) and target else None


def registered_targets(group: str) -> frozenset[str]:
    """The class paths that the options of `group` name as their `_target_`.

    Not cached: a few small files are read per call, and a plugin installed while a
    notebook runs is then seen by the next model loaded.
    """
    targets = (target_of(path) for _, path in group_files(group))
    return frozenset(target for target in targets if target is not None)
