"""Reports name the positions' unit honestly: no metres for a non-metric dataset.

A COLMAP model has no scale of its own (relocfw.data.colmap). Its runs must not say
metres anywhere a user reads: no `_m` keys or columns, no "(m)" titles, no metre
bands or shares; the units note is written once into each report as it is made
(never added afterwards to whatever files a folder holds); and a model declared
metric (`dataset.metric=true`) gets the metre names back and no note.
"""

from __future__ import annotations

import csv
import io
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from relocfw.core.values import Crop, Localization, Pose
from relocfw.data.colmap import UNITS_NOTE
from relocfw.data.frames import Frame
from relocfw.report.evaluation import MethodResult
from tests.cli_runs import relocfw
from tests.conftest import TINY_MODEL
from tests.data.test_colmap import named_poses, project

# What says metres in a report: a key or column in metres (`position_error_m`,
# `median_position_m_rejecting_10%`), a title in metres ("med pos (m)", "(m, deg)"),
# or a metre band or share (`within_0.05m_5deg`, "25cm/2deg", `share_position_above_1m`).
METRE_WORDS = re.compile(r"_m(?![A-Za-z0-9])|\(m[,)]|(?<![\d.])\d+(?:\.\d+)?c?m(?![A-Za-z0-9])")
REPORT_SUFFIXES = (".txt", ".md", ".csv", ".json")
NOTE_LINE = f"Note: {UNITS_NOTE}."


def reports(run_dir: Path) -> dict[str, str]:
    """name -> text of every report file a run wrote at the top of `run_dir`."""
    return {
        path.name: path.read_text()
        for path in sorted(run_dir.iterdir())
        if path.is_file() and path.suffix in REPORT_SUFFIXES
    }


def metre_words(text: str) -> list[str]:
    return sorted({match.group(0) for match in METRE_WORDS.finditer(text)})


def assert_no_metres(files: dict[str, str]) -> None:
    """No report says metres: no `_m` key or column, no "(m)" title, no metre band."""
    for name, text in files.items():
        assert metre_words(text) == [], name


def assert_one_note(files: dict[str, str]) -> None:
    """Every report says the units note once, where its kind of file says things
    (text and JSON reports first: the note's own places)."""
    for name, text in sorted(files.items(), key=lambda item: item[0].endswith(".csv")):
        if name.endswith((".txt", ".md")):
            assert text.count("Note:") == 1 and text.startswith(NOTE_LINE + "\n"), name
        elif name.startswith("summary") and name.endswith(".json"):
            rows = json.loads(text)
            assert text.count(UNITS_NOTE) == len(rows), name
            assert [row["units_note"] for row in rows] == [UNITS_NOTE] * len(rows), name
        elif name.endswith(".json"):
            assert text.count(UNITS_NOTE) == 1, name
            assert json.loads(text)["units_note"] == UNITS_NOTE, name
        elif name.startswith("summary"):
            rows = list(csv.DictReader(io.StringIO(text)))
            assert [row["units_note"] for row in rows] == [UNITS_NOTE] * len(rows), name
        else:
            # Per-query and comparison CSVs: the unit is in the column names.
            header = text.splitlines()[0]
            assert UNITS_NOTE not in text, name
            assert "_units" in header or "(model units" in header, name


@pytest.fixture(scope="module")
def colmap_project(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A COLMAP project of 20 tiny images; seq3 is the test split."""
    root = tmp_path_factory.mktemp("colmap") / "project"
    names = [f"seq{s}/{i:02d}.png" for s in (1, 2) for i in range(8)]
    project(root, named_poses(names + [f"seq3/{i:02d}.png" for i in range(4)]), binary=True)
    return root


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One cache for the module: the runs share one trained model."""
    return tmp_path_factory.mktemp("units-cache")


def colmap_run(project_root: Path, run_dir: Path, cache: Path, *extra: str):
    args = [
        *TINY_MODEL,
        "dataset=colmap",
        f"dataset.root={project_root}",
        "dataset.test=[seq3/*]",
        f"hydra.run.dir={run_dir}",
        *extra,
    ]
    return relocfw(args, run_dir.parent, cache)


RELOCALIZE_REPORTS = ("results.csv", "summary.csv", "summary.json", "table.txt")
DIAGNOSE_REPORTS = ("diagnose.json", "diagnose.md", "diagnose_windows.csv")


@pytest.fixture(scope="module")
def used_dir(colmap_project: Path, cache: Path, tmp_path_factory: pytest.TempPathFactory):
    """One run folder used again and again, as a fixed hydra.run.dir is: a metric run's
    reports below it, then task=diagnose and task=relocalize twice on the COLMAP model.

    Returns:
        The folder and the three runs' outputs.
    """
    run_dir = tmp_path_factory.mktemp("used") / "run"
    earlier = run_dir / "earlier"
    earlier.mkdir(parents=True)
    (earlier / "table.txt").write_text("method  med pos (m)\n")
    (earlier / "summary.json").write_text('[{"median_position_m": 0.1}]')
    diagnose = ("task=diagnose", "diagnose.curve_queries=1", "diagnose.table3_queries=1")
    outputs = [colmap_run(colmap_project, run_dir, cache, *diagnose)]
    outputs += [colmap_run(colmap_project, run_dir, cache) for _ in range(2)]
    for result in outputs:
        assert result.returncode == 0, result.stderr
    return run_dir, outputs


def test_runs_into_a_used_folder_note_each_report_once(used_dir):
    run_dir, outputs = used_dir
    files = reports(run_dir)
    assert sorted(files) == sorted(DIAGNOSE_REPORTS + RELOCALIZE_REPORTS)
    assert_one_note(files)
    # Another run's files in the folder are left as they were.
    assert (run_dir / "earlier" / "table.txt").read_text() == "method  med pos (m)\n"
    assert (run_dir / "earlier" / "summary.json").read_text() == '[{"median_position_m": 0.1}]'
    assert all(result.stdout.count(UNITS_NOTE) == 1 for result in outputs)


def test_a_colmap_relocalization_names_no_metres(used_dir):
    run_dir, _ = used_dir
    files = reports(run_dir)
    assert_no_metres({name: files[name] for name in RELOCALIZE_REPORTS})
    assert "med pos (model units)" in files["table.txt"]
    summary = json.loads(files["summary.json"])
    assert "median_position_units" in summary[0] and "within_0.25m_2deg" not in summary[0]
    # Orientation-only shares mean the same at any scale: they stay.
    assert "share_orientation_below_15deg" in summary[0]
    assert "position_error_units" in files["results.csv"].splitlines()[0]


def test_a_colmap_diagnosis_names_no_metres(used_dir):
    run_dir, _ = used_dir
    files = reports(run_dir)
    assert_no_metres({name: files[name] for name in DIAGNOSE_REPORTS})
    assert "| median pos (model units) |" in files["diagnose.md"]
    errors = json.loads(files["diagnose.json"])["scenes"]["colmap"]["errors"]
    assert "median_position_units" in errors["centre"]
    assert "position_error_units" in files["diagnose_windows.csv"].splitlines()[0]


def test_a_colmap_model_declared_metric_reports_metres_without_a_note(
    used_dir, colmap_project, cache, tmp_path
):
    # A copy of the used folder, so the other tests see it as the fixture left it.
    run_dir = tmp_path / "run"
    shutil.copytree(used_dir[0], run_dir)
    result = colmap_run(colmap_project, run_dir, cache, "dataset.metric=true")
    assert result.returncode == 0, result.stderr
    assert UNITS_NOTE not in result.stdout and "note:" not in result.stdout
    files = reports(run_dir)
    for name in RELOCALIZE_REPORTS:
        text = files[name]
        assert UNITS_NOTE not in text and "units_note" not in text and "Note:" not in text, name
        assert "model units" not in text and "_units" not in text, name
    assert files["table.txt"].startswith("method ") and "med pos (m)" in files["table.txt"]
    summary = json.loads(files["summary.json"])
    for key in ("median_position_m", "within_0.25m_2deg", "share_position_below_0.5m"):
        assert key in summary[0], key
    assert "position_error_m" in files["results.csv"].splitlines()[0]
    # The non-metric diagnosis beside it keeps its own note, once, untouched.
    for name in DIAGNOSE_REPORTS:
        assert files[name] == (used_dir[0] / name).read_text(), name


def test_a_colmap_comparison_names_no_metres_and_notes_once(colmap_project, cache, tmp_path):
    run_dir = tmp_path / "compare"
    methods = '+compare.methods={PoseNet:["crop=centre"],GA:["crop=ga"]}'
    result = colmap_run(
        colmap_project,
        run_dir,
        cache,
        "task=compare",
        "~compare.methods",
        methods,
        "compare.crop_seeds=[0,1]",
    )
    assert result.returncode == 0, result.stderr
    files = reports(run_dir)
    for name in ("comparison.md", "comparison.csv", "comparison.json", "crop_seeds.md"):
        assert name in files, name
    assert {"table_colmap.txt", "summary_colmap.json", "results_colmap.csv"} <= set(files)
    assert_no_metres(files)
    assert_one_note(files)
    assert "PoseNet (model units, deg)" in files["comparison.md"]
    spread = json.loads(files["comparison.json"])["scenes"]["colmap"]["crop_seed_spread"]["GA"]
    assert len(spread["median_position_units"]) == 2
    assert result.stdout.count(UNITS_NOTE) == 1


# ------------------------------------------------------- writers, without the CLI


IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def answered(method: str, errors: list[float], spread: float = float("nan")) -> MethodResult:
    """A result whose per-query position errors (along x) are as given."""
    truth = [Frame(f"q{i}", Path(f"q{i}.png"), Pose([0.0, i, 0.0], IDENTITY)) for i in range(4)]
    answers = tuple(
        Localization(Pose([e, i, 0.0], IDENTITY), Crop(0, 0, 1), 0.0, 1, 0.0, spread * e, spread)
        for i, e in enumerate(errors)
    )
    return MethodResult(method, tuple(truth), answers)


def test_the_seed_comparison_names_no_metres(tmp_path):
    from relocfw.app.tasks.compare import write_seed_comparison
    from relocfw.report.units import model_units

    results = {
        seed: {
            "hall_5m": {
                "Ref": answered("Ref", [0.1 + seed, 0.2, 0.3, 0.4]),
                "GA 1m": answered("GA 1m", [0.05, 0.1 + seed, 0.2, 0.3]),
            }
        }
        for seed in (0, 1, 2)
    }
    floor = answered("mean training pose", [1.0] * 4)
    report = write_seed_comparison(
        results, {"hall_5m": floor}, "Ref", tmp_path, unit=model_units(UNITS_NOTE)
    )
    # The user's scene and method names are kept as they are, metres or not.
    stats = report["scenes"]["hall_5m"]["GA 1m"]
    assert "median_position_units" in stats and "position_units" in stats["vs_reference"]
    files = reports(tmp_path)
    for name in files:
        files[name] = files[name].replace("hall_5m", "hall").replace("GA 1m", "GA")
    assert_no_metres(files)
    assert_one_note(files)
    assert "diff of medians (model units)" in files["comparison.md"]
    assert "Wilcoxon" in files["comparison.md"]  # the footnote is kept


class Labels:
    """Every label, title and legend text of the figures `save` is handed."""

    def __init__(self) -> None:
        self.texts: list[str] = []

    def save(self, figure, path: Path) -> Path:
        texts = [text.get_text() for text in figure.texts]
        for axis in figure.axes:
            texts += [axis.get_xlabel(), axis.get_ylabel(), axis.get_title()]
            legend = axis.get_legend()
            if legend is not None:
                texts += [text.get_text() for text in legend.get_texts()]
        self.texts += texts
        Path(path).write_bytes(b"png")
        return Path(path)


@pytest.fixture
def labels(monkeypatch) -> Labels:
    from relocfw.report import diagnose_figures, figures

    seen = Labels()
    monkeypatch.setattr(figures, "save", seen.save)
    monkeypatch.setattr(diagnose_figures, "save", seen.save)
    return seen


def diagnosed_queries():
    from relocfw.report.diagnosis import QueryWindows, picks_of

    crops = np.array([[0, 0, 36], [6, 0, 36], [12, 0, 36]])
    queries = [
        QueryWindows(
            frame=f"q{i}",
            crops=crops,
            views=crops.astype(float),
            distances=np.array([0.3, 0.1, 0.2]),
            position_errors=np.array([0.4, 0.2, 0.9]) * (i + 1),
            orientation_errors=np.array([3.0, 2.0, 5.0]),
            centre=1,
            windows=3,
        )
        for i in range(2)
    ]
    return queries, picks_of(queries)


def test_figures_label_positions_in_the_runs_unit(labels, tmp_path):
    from relocfw.report import diagnose_figures, figures
    from relocfw.report.units import model_units

    unit = model_units(UNITS_NOTE)
    sampled = answered("Bayes", [0.1, 0.4, 0.2, 0.8], spread=0.5)
    plain = answered("Ref", [0.3, 0.6, 1.2, 2.0])
    quality = {
        kind: {
            "spearman_spread_error": 1.0,
            "ause": 0.0,
            "sparsification": {"fractions": [0, 0.5], "by_uncertainty": [1, 2], "oracle": [1, 2]},
        }
        for kind in ("position", "orientation")
    }
    figures.error_histogram([plain, sampled], "position", tmp_path / "h.png", unit=unit)
    figures.error_curves([plain, sampled], tmp_path / "c.png", unit=unit)
    figures.trajectory_top_down(list(plain.frames), [plain], tmp_path / "t.png", unit=unit)
    figures.uncertainty_against_error(sampled, quality, tmp_path / "u.png", unit=unit)
    figures.training_curve(
        {"loss": [1.0, 0.5], "main_position_m": [2.0, 1.0], "main_orientation": [0.2, 0.1]},
        tmp_path / "curve.png",
        unit=unit,
    )
    queries, picks = diagnosed_queries()
    diagnose_figures.distance_vs_error(queries, picks, tmp_path / "d.png", unit=unit)
    diagnose_figures.offset_curves(queries, picks, [0], tmp_path / "o.png", unit=unit)
    images = [np.zeros((36, 48, 3), np.uint8)] * 2
    diagnose_figures.crops_on_images(queries, picks, images, [0], tmp_path / "i.png", unit=unit)
    text = "\n".join(labels.texts)
    assert "position error (model units)" in text and "x (model units)" in text
    assert "0.200 model units" in text  # the offset curves' and crops' legends
    # No metre unit and no metre threshold (the histogram's 0.5 m / 1 m shares).
    assert re.findall(r"\(m\)|\d m\b| m,|\bm\)", text) == []
    assert "< 0.5" not in text and "> 1 " not in text


def test_metric_figures_keep_their_metre_labels(labels, tmp_path):
    from relocfw.report import figures

    plain = answered("Ref", [0.3, 0.6, 1.2, 2.0])
    figures.error_histogram([plain], "position", tmp_path / "h.png")
    figures.error_curves([plain], tmp_path / "c.png")
    text = "\n".join(labels.texts)
    assert "position error (m)" in text and "25% < 0.5 m, 50% > 1 m" in text


def test_a_colmap_model_is_model_units_unless_declared_metric(colmap_project):
    from relocfw.core.errors import ConfigError
    from relocfw.data.colmap import ColmapDataset
    from relocfw.report.units import METRES, unit_of

    plain = ColmapDataset(str(colmap_project), test=["seq3/*"])
    assert unit_of(plain).name == "model units" and unit_of(plain).note == UNITS_NOTE
    aligned = ColmapDataset(str(colmap_project), test=["seq3/*"], metric=True)
    assert unit_of(aligned) == METRES and aligned.units_note == ""
    with pytest.raises(ConfigError, match="dataset.metric must be true or false, got 'yes'"):
        ColmapDataset(str(colmap_project), test=["seq3/*"], metric="yes")
