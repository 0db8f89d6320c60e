"""The package tree is the design: six parts, imports running one way, no cycle.

Every `import` in relocfw/ is read from the source (function-level ones too, since a
lazy import hides a cycle without removing it), so the checks hold for code paths
the other tests never run.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
from pathlib import Path

import pytest

import relocfw

PACKAGE = Path(relocfw.__file__).parent
PARTS = ("core", "model", "data", "report", "structure", "serve", "app")
# What each part may import besides itself: app -> report -> model, data -> core.
MAY_IMPORT = {
    "core": set(),
    "model": {"core"},
    "data": {"core"},
    "report": {"core", "model", "data"},
    "structure": {"core", "data"},
    # The HTTP service (task=serve) answers with a loaded Relocalizer; the app loads it.
    "serve": {"core"},
    "app": {"core", "model", "data", "report", "structure", "serve", "plugins"},
}
# Modules beside the parts: the package's facade and entry point, and the service's
# client, which a robot imports without relocfw's own stack (it imports no relocfw).
STANDALONE = ("relocfw", "relocfw.__main__", "relocfw.client")


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def relocfw_imports(path: Path) -> set[str]:
    """The relocfw modules `path` imports: `from relocfw.x import y` names relocfw.x.y
    when y is a module of its own, else relocfw.x."""
    tree = ast.parse(path.read_text(), str(path))
    # Imports under `if TYPE_CHECKING:` name types for annotations and never run.
    typing_only = {
        id(inner)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING"
        for inner in ast.walk(node)
    }
    found = set()
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.split(".")[0] == "relocfw"}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module.split(".")[0] != "relocfw":
                continue
            for alias in node.names:
                child = f"{node.module}.{alias.name}"
                found.add(
                    child
                    if (PACKAGE.parent / child.replace(".", "/")).with_suffix(".py").exists()
                    else node.module
                )
    return found


MODULES = {
    module_name(path): relocfw_imports(path)
    for path in sorted(PACKAGE.rglob("*.py"))
    if "__pycache__" not in path.parts
}


def part_of(module: str) -> str:
    """'core', 'model', ... ; 'facade' for relocfw itself and relocfw.__main__."""
    pieces = module.split(".")
    return pieces[1] if len(pieces) > 2 or (len(pieces) == 2 and pieces[1] in PARTS) else "facade"


def test_the_import_reader_sees_imports():
    # A reader that found nothing would pass every check below.
    assert "relocfw.core.interfaces" in MODULES["relocfw.core.pipeline"]
    assert "relocfw.model.model_file" in MODULES["relocfw.app.tasks.localize"]
    assert "relocfw.core.pipeline" not in MODULES["relocfw.core.search_loop"]
    assert sum(len(targets) for targets in MODULES.values()) > 150


def test_no_relative_imports():
    # The reader resolves absolute imports only; relative ones would go unchecked.
    relative = [
        module_name(path)
        for path in PACKAGE.rglob("*.py")
        if "__pycache__" not in path.parts
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.ImportFrom) and node.level > 0
    ]
    assert not relative, f"relative imports in {sorted(set(relative))}"


def test_every_module_lives_in_one_of_the_five_parts():
    loose = [m for m in MODULES if part_of(m) == "facade" and m not in STANDALONE]
    assert not loose, f"modules outside {', '.join(PARTS)}: {loose}"
    assert not MODULES["relocfw.client"], "relocfw.client must not import relocfw's stack"
    assert {part_of(m) for m in MODULES} == {*PARTS, "facade"}


@pytest.mark.parametrize("part", PARTS)
def test_imports_run_one_way(part):
    wrong = sorted(
        f"{module} imports {target}"
        for module, targets in MODULES.items()
        if part_of(module) == part
        for target in targets
        if part_of(target) not in MAY_IMPORT[part] | {part}
    )
    assert not wrong, f"{part} may import only {sorted(MAY_IMPORT[part])}: {wrong}"


def test_no_import_cycle():
    graph = {m: {t for t in targets if t in MODULES and t != m} for m, targets in MODULES.items()}
    # Parents are imported before their children; the facade imports the parts, and a
    # part's module imports the facade's package only as a parent, not as an edge.
    graph = {m: {t for t in targets if part_of(t) != "facade"} for m, targets in graph.items()}
    state: dict[str, str] = {}
    path: list[str] = []

    def visit(module: str) -> None:
        state[module] = "open"
        path.append(module)
        for target in sorted(graph[module]):
            if state.get(target) == "open":
                cycle = path[path.index(target) :] + [target]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if target not in state:
                visit(target)
        path.pop()
        state[module] = "done"

    for module in sorted(graph):
        if module not in state:
            visit(module)


def module_sources() -> dict[str, Path]:
    """Every module of relocfw, with the packages installed beside it (relocfw.plugins,
    relocfw.conf), wherever the install put their folders."""
    sources = {}
    for package in ("relocfw", "relocfw.plugins", "relocfw.conf"):
        root = Path(importlib.util.find_spec(package).submodule_search_locations[0])
        for path in sorted(root.rglob("*.py")):
            if "__pycache__" in path.parts:
                continue
            parts = path.relative_to(root).with_suffix("").parts
            parts = parts[:-1] if parts[-1] == "__init__" else parts
            sources.setdefault(".".join((package, *parts)), path)
    return sources


def import_time_statements(body: list[ast.stmt]):
    """The statements a module runs when it is imported: its body and the bodies of
    its classes, ifs, loops, trys and withs, not functions (they run later) nor
    `if TYPE_CHECKING:` blocks (they never run)."""
    for node in body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            yield from import_time_statements(node.orelse)
            continue
        yield node
        for field in ("body", "orelse", "finalbody"):
            yield from import_time_statements(getattr(node, field, None) or [])
        for handler in getattr(node, "handlers", None) or []:
            yield from import_time_statements(handler.body)


def import_time_edges(sources: dict[str, Path]) -> dict[str, set[str]]:
    """module -> the relocfw modules it imports while it is imported. `from p import x`
    names p.x when that is a module, else p itself (x is an attribute p must already
    have: the edge a cycle breaks on). A package's own import of its parent (implied by
    any import of a submodule) is no edge: Python gives the half-built parent."""
    graph = {}
    for module, path in sources.items():
        targets = set()
        for node in import_time_statements(ast.parse(path.read_text(), str(path)).body):
            if isinstance(node, ast.Import):
                targets |= {a.name for a in node.names if a.name.split(".")[0] == "relocfw"}
            elif isinstance(node, ast.ImportFrom) and node.module:
                if node.level:
                    raise AssertionError(f"{module}: relative import")
                if node.module.split(".")[0] != "relocfw":
                    continue
                for alias in node.names:
                    child = f"{node.module}.{alias.name}"
                    targets.add(child if child in sources else node.module)
        graph[module] = {t for t in targets if t in sources and t != module}
    return graph


def test_no_import_cycle_when_anything_is_imported():
    """The import-time graph of every module, the facade and the plugins included,
    has no cycle: importing any module first (a plugin, a script's `from relocfw.app
    import cli`) never meets a half-built module whose names it needs."""
    sources = module_sources()
    assert {"relocfw", "relocfw.plugins.ga_crop", "relocfw.conf", "relocfw.app.cli"} <= set(sources)
    graph = import_time_edges(sources)
    assert "relocfw.core.pipeline" in graph["relocfw"]  # the reader sees the facade's
    assert "relocfw.app.config_schema" in graph["relocfw.conf"]
    state: dict[str, str] = {}
    path: list[str] = []

    def visit(module: str) -> None:
        state[module] = "open"
        path.append(module)
        for target in sorted(graph[module]):
            if state.get(target) == "open":
                cycle = path[path.index(target) :] + [target]
                raise AssertionError("import-time cycle: " + " -> ".join(cycle))
            if target not in state:
                visit(target)
        path.pop()
        state[module] = "done"

    for module in sorted(graph):
        if module not in state:
            visit(module)


def test_the_pipeline_does_not_know_the_model_file():
    # The file format builds on the Relocalizer; the reverse edge was the old cycle.
    assert "relocfw.model.model_file" not in MODULES["relocfw.core.pipeline"]


@pytest.mark.parametrize("flat", sorted(relocfw.FLAT_PATHS))
def test_plugins_written_for_the_flat_paths_still_import(flat):
    old = importlib.import_module(f"relocfw.{flat}")
    assert old is importlib.import_module(relocfw.FLAT_PATHS[flat])


# Names plugins and scripts imported from the flat paths of relocfw 0.1 (a frozen list:
# the moved modules must still hold them).
NAMES_OF_0_1 = {
    "interfaces": [
        "Backbone",
        "CropSearch",
        "SimilarityIndex",
        "CropDistance",
        "crop_at",
        "crop_side_and_span",
        "query_seed",
    ],
    "values": ["Crop", "Pose", "PoseOutput", "Localization"],
    "errors": ["ConfigError", "DataError", "RelocfwError"],
    "options": ["integer_at_least", "probability", "real_number"],
    "imaging": ["Strip", "read_rgb", "to_network_input"],
    "standardise": ["ZScore", "check_features", "nearest", "k_nearest"],
    "checkpoints": ["read_torch_file", "save_atomic"],
    "pose_head": [
        "PoseHead",
        "PoseRegressor",
        "dropout_variant_of",
        "mean_quaternions",
        "sample_statistics",
    ],
    "contracts": ["check_backbone", "check_crop_search", "check_similarity_index"],
    "sampling": ["monte_carlo"],
    "window_pooling": ["StripMaps"],
    "pipeline": ["Relocalizer"],
}


@pytest.mark.parametrize("flat", sorted(NAMES_OF_0_1))
def test_the_names_of_0_1_are_still_there(flat):
    module = importlib.import_module(f"relocfw.{flat}")
    missing = [name for name in NAMES_OF_0_1[flat] if not hasattr(module, name)]
    assert not missing, f"relocfw.{flat} lost {missing}"
    assert getattr(relocfw, flat) is module  # relocfw.interfaces.Backbone works too


def test_the_public_names_stay_importable_from_the_top():
    from relocfw import Backbone, CropSearch, Relocalizer, SimilarityIndex, load_model
    from relocfw.interfaces import Backbone as FlatBackbone

    assert FlatBackbone is Backbone
    assert callable(load_model) and Relocalizer and CropSearch and SimilarityIndex


def test_only_the_app_sees_hydra_or_omegaconf():
    def third_party(path: Path) -> set[str]:
        names = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
        return names

    seeing = sorted(
        module_name(path)
        for path in PACKAGE.rglob("*.py")
        if "__pycache__" not in path.parts
        and part_of(module_name(path)) != "app"
        and third_party(path) & {"hydra", "omegaconf"}
    )
    assert not seeing, f"Hydra/OmegaConf outside relocfw.app: {seeing}"
