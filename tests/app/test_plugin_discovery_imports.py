"""Plugin discovery reads metadata and folders only: a plugin package whose __init__
raises must neither hide its YAML nor break loading every other model."""

import sys

import pytest

from relocfw import Relocalizer, load_model, save_model
from relocfw.app.plugin_discovery import discover_options
from relocfw.core.plugin_registry import group_files, package_folder, registered_targets
from tests.cli_runs import relocfw
from tests.model.test_model_file_trust import OPTIONS, tiny_relocalizer

PACKAGE = "raising_plugin"


@pytest.fixture
def raising_site(tmp_path, monkeypatch):
    """An installed plugin (a dist-info with the entry point) whose package's
    __init__ raises: importing it, even to find its conf folder, fails."""
    site = tmp_path / "site"
    info = site / "raisingplug-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: raisingplug\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[relocfw.configs]\nmain = {PACKAGE}.conf\n")
    files = {
        "__init__.py": "raise RuntimeError('raising_plugin ran at discovery')\n",
        "conf/__init__.py": "",
        "conf/crop/raising.yaml": f"# Never imported by discovery.\n_target_: {PACKAGE}.Crop\n",
    }
    for name, body in files.items():
        (site / PACKAGE / name).parent.mkdir(parents=True, exist_ok=True)
        (site / PACKAGE / name).write_text(body)
    monkeypatch.syspath_prepend(str(site))
    discover_options.cache_clear()
    yield site
    discover_options.cache_clear()
    sys.modules.pop(PACKAGE, None)


def test_discovery_finds_the_yaml_without_running_the_plugin(raising_site):
    assert package_folder(f"{PACKAGE}.conf") == raising_site / PACKAGE / "conf"
    assert any(path.name == "raising.yaml" for _, path in group_files("crop"))
    assert f"{PACKAGE}.Crop" in registered_targets("crop")
    assert any(o.name == "raising" and o.group == "crop" for o in discover_options())
    assert PACKAGE not in sys.modules  # its __init__ never ran


def test_a_raising_plugin_does_not_break_loading_other_models(raising_site, tmp_path):
    path = save_model(tmp_path / "model.relocfw", tiny_relocalizer(), OPTIONS, {})
    assert isinstance(load_model(path), Relocalizer)


def test_the_cli_lists_plugins_with_a_raising_plugin_installed(raising_site, tmp_path):
    result = relocfw(["task=plugins"], tmp_path, PYTHONPATH=str(raising_site))
    assert result.returncode == 0, result.stderr
    assert "raising" in result.stdout and "[raisingplug]" in result.stdout


def test_a_config_package_found_only_by_importing_a_raising_parent_is_left_out(raising_site):
    # No such subfolder: the full-name lookup (for editable installs that map the
    # config package elsewhere) imports the parent, whose failure stays contained.
    assert package_folder(f"{PACKAGE}.elsewhere") is None
    assert any(path.name == "raising.yaml" for _, path in group_files("crop"))
