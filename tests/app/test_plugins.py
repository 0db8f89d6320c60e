"""Third-party plugins, seen from outside relocfw: installed, listed, chosen, broken."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

from relocfw.core.contracts import check_crop_search
from tests.cli_runs import relocfw
from tests.conftest import TINY_OVERRIDES

GUIDE = Path(__file__).resolve().parents[2] / "docs" / "plugins.md"


def with_path(args, tmp_path, site):
    """Run the CLI with `site` on PYTHONPATH: the plugin is installed there."""
    return relocfw(args, tmp_path, PYTHONPATH=str(site))


def guide_files():
    """The files the guide's code blocks spell out (blocks starting `# file: PATH`)."""
    blocks = re.findall(r"```[a-z]*\n(.*?)```", GUIDE.read_text(), flags=re.S)
    files = {}
    for block in blocks:
        first, _, body = block.partition("\n")
        if first.startswith("# file: "):
            files[first[len("# file: ") :].strip()] = body
    return files


def test_a_plugin_written_from_the_guide_works(tmp_path, monkeypatch):
    source, site = tmp_path / "relocfw-leftmost", tmp_path / "site"
    for name, body in guide_files().items():
        (source / name).parent.mkdir(parents=True, exist_ok=True)
        (source / name).write_text(body)
    assert (source / "relocfw_leftmost" / "conf" / "crop" / "leftmost.yaml").is_file()
    install = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            str(site),
            str(source),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert install.returncode == 0, install.stderr
    result = with_path([*TINY_OVERRIDES, "crop=leftmost", "crop.count=5"], tmp_path, site)
    assert result.returncode == 0, result.stderr
    assert "leftmost + kmeans (k=4)" in result.stdout
    listing = with_path(["task=plugins"], tmp_path, site)
    assert re.search(r"leftmost\s+\[relocfw-leftmost\] Best of the three", listing.stdout)
    # The guide's contract test, run on the guide's class.
    monkeypatch.syspath_prepend(str(site))
    from relocfw_leftmost.search import LeftmostCrop

    check_crop_search(LeftmostCrop())
    # Uninstalled (not on the path): the same command names the crop options there are.
    gone = relocfw([*TINY_OVERRIDES, "crop=leftmost"], tmp_path)
    assert gone.returncode != 0
    assert "Could not find 'crop/leftmost'" in gone.stderr
    assert "centre" in gone.stderr and "sweep" in gone.stderr


def fake_install(site, distribution, package, files):
    """What pip leaves behind, written by hand: a dist-info with the entry point."""
    info = site / f"{distribution}-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {distribution}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[relocfw.configs]\nmain = {package}.conf\n")
    for name, body in {"__init__.py": "", "conf/__init__.py": "", **files}.items():
        (site / package / name).parent.mkdir(parents=True, exist_ok=True)
        (site / package / name).write_text(body)


@pytest.fixture
def broken_site(tmp_path):
    site = tmp_path / "site"
    target = "_target_: broken_plugin"
    files = {
        "search.py": "raise ImportError('broken_plugin needs libfoo')\n",
        "plain.py": "class NotASearch:\n    def find(self, width, height, distance): ...\n",
        "conf/crop/broken.yaml": f"# Fails to import.\n{target}.search.Broken\n",
        "conf/crop/plain.yaml": f"# Not a CropSearch.\n{target}.plain.NotASearch\n",
        "conf/crop/ga.yaml": f"# Clashes with the built-in.\n{target}.search.Broken\n",
    }
    fake_install(site, "brokenplug", "broken_plugin", files)
    return site


def test_a_broken_plugin_fails_only_when_chosen(tmp_path, broken_site):
    fine = with_path([*TINY_OVERRIDES, "crop=centre", "task=train"], tmp_path, broken_site)
    assert fine.returncode == 0, fine.stderr
    broken = with_path([*TINY_OVERRIDES, "crop=broken"], tmp_path, broken_site)
    assert broken.returncode == 2
    assert "crop=broken (from brokenplug)" in broken.stderr
    assert "broken_plugin needs libfoo" in broken.stderr
    assert "model:" not in broken.stdout  # refused before training


def test_an_object_that_is_not_the_interface_is_named(tmp_path, broken_site):
    result = with_path([*TINY_OVERRIDES, "crop=plain"], tmp_path, broken_site)
    assert result.returncode == 2
    assert (
        "crop=plain (from brokenplug): broken_plugin.plain.NotASearch does not implement "
        "relocfw.CropSearch (subclass it); it lacks propose or search" in result.stderr
    )
    assert "model:" not in result.stdout


def test_clashing_options_are_reported(tmp_path, broken_site):
    result = with_path(["task=plugins"], tmp_path, broken_site)
    assert result.returncode == 0, result.stderr
    assert (
        "warning: crop=ga is offered by relocfw and brokenplug; relocfw's is used" in result.stderr
    )
    assert re.search(r"broken\s+\[brokenplug\] Fails to import\.", result.stdout)
    help_text = with_path(["--help"], tmp_path, broken_site).stdout
    assert "[brokenplug]" in help_text and "conflicts:" in help_text


def test_example_plugin_end_to_end(tmp_path):
    pytest.importorskip(
        "relocfw_coarse_to_fine", reason="pip install -e examples/relocfw-coarse-to-fine"
    )
    overrides = [o for o in TINY_OVERRIDES if not o.startswith("k=")]
    result = relocfw([*overrides, "crop=coarse_to_fine", "index=kmeans", "k=10"], tmp_path)
    assert result.returncode == 0, result.stderr
    assert "coarse_to_fine + kmeans (k=10)" in result.stdout
