"""benchmarks/readme_tables.py: the README's method table and the +- cells of
docs/results/structure.md agree with the committed results files, and the check names
the row where a page and the files differ."""

from __future__ import annotations

import importlib
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BENCHMARKS = ROOT / "benchmarks"


@pytest.fixture
def readme_tables(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    return importlib.import_module("readme_tables")


def pages_copy(tmp_path: Path) -> Path:
    """README.md and docs/results/structure.md under tmp_path; the results files stay
    the repository's (the script reads them from its own root)."""
    for page in ("README.md", "docs/results/structure.md"):
        (tmp_path / page).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / page, tmp_path / page)
    return tmp_path


def test_readme_and_structure_page_agree_with_the_results_files(readme_tables):
    assert readme_tables.check() == []


def test_an_edited_readme_number_is_reported_with_its_row(readme_tables, tmp_path):
    root = pages_copy(tmp_path)
    readme = root / "README.md"
    row = "| PoseNet (centre crop) | `crop=centre` | [0.181 / 6.90][families]"
    assert row in readme.read_text()
    readme.write_text(readme.read_text().replace(row, row.replace("0.181", "0.174")))
    problems = readme_tables.check(root)
    assert len(problems) == 1
    assert "README.md: row 'PoseNet (centre crop) | `crop=centre`' differs" in problems[0]
    assert "[0.174 / 6.90][families]" in problems[0]  # what the page says
    assert "[0.181 / 6.90][families]" in problems[0]  # what the files say


def test_a_population_std_cell_is_reported_and_rewritten(readme_tables, tmp_path):
    root = pages_copy(tmp_path)
    page = root / "docs/results/structure.md"
    sample = "| near | PoseNet | 0.181 +- 0.026 | 6.90 +- 0.54 |"
    population = "| near | PoseNet | 0.181 +- 0.021 | 6.90 +- 0.44 |"
    assert sample in page.read_text()
    # The first such row is the marked rgb-chosen table's.
    page.write_text(page.read_text().replace(sample, population, 1))
    problems = readme_tables.check(root)
    assert problems and all("row 'near | PoseNet' differs" in p for p in problems)
    assert readme_tables.write(root) == [Path("docs/results/structure.md")]
    assert readme_tables.check(root) == []
    assert population not in page.read_text()


def test_a_table_without_its_markers_is_one_message(readme_tables, tmp_path):
    root = pages_copy(tmp_path)
    readme = root / "README.md"
    readme.write_text(readme.read_text().replace(readme_tables.TABLE_END, ""))
    assert readme_tables.check(root) == [
        f"README.md: expected one {readme_tables.TABLE_START!r} and one {readme_tables.TABLE_END!r}"
    ]


def test_sample_std_over_seeds(readme_tables):
    medians = readme_tables.Medians((0.19630851, 0.19472348, 0.15116723), (7.0, 7.0, 7.0))
    assert medians.spread_cells() == ("0.181 +- 0.026", "7.00 +- 0.00")
