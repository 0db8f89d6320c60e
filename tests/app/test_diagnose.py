"""task=diagnose: the headroom numbers, the per-offset scoring and the CLI's files."""

import csv
import json
import math

import numpy as np
import pytest

from relocfw import QueryOptions, Relocalizer
from relocfw.core.geometry import orientation_error_deg, position_error
from relocfw.core.json_output import json_ready
from relocfw.core.values import Pose
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.sweep_crop import SweepCrop
from relocfw.report.diagnosis import (
    diagnose,
    pick,
    picks_of,
    pose_errors,
    spearman,
    summarise_headroom,
)
from relocfw.report.window_recording import load_windows
from tests.cli_runs import relocfw, relocfw_here
from tests.conftest import TINY_OVERRIDES
from tests.core.test_pipeline import CountingPoseNet


def constructed_queries():
    """Three queries whose picks, shares and correlations are worked out by hand."""
    truth = Pose([0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
    # Query 1's first window has a NaN pose: it must count as infinitely wrong.
    position, orientation = pose_errors(
        [[np.nan, 0, 0], [0.4, 0, 0], [0.2, 0, 0]],
        [[1, 0, 0, 0], [1, 0, 0, 0], [1, 0, 0, 0]],
        truth,
    )
    orientation = np.array([orientation[0], 10.0, 20.0])  # keep the inf, set the rest
    distances = [
        np.array([0.9, 0.2, 0.5, 0.7, 0.8]),
        np.array([0.1, 0.4, 0.9]),
        np.array([0.3, 0.05, 0.2]),
    ]
    positions = [np.array([0.6, 0.3, 0.5, 0.2, 0.9]), position, np.array([0.3, 0.1, 0.2])]
    orientations = [np.array([5.0, 4, 3, 2, 1]), orientation, np.array([3.0, 2, 1])]
    return distances, positions, orientations, [2, 1, 1]


def test_a_nan_pose_is_infinitely_wrong_never_dropped():
    distances, positions, orientations, _ = constructed_queries()
    assert positions[1][0] == math.inf and orientations[1][0] == math.inf
    assert positions[1][1:] == pytest.approx([0.4, 0.2])
    position, orientation = pose_errors([[0, 0, 0]], [[0, 0, 0, 0]], Pose([0, 0, 0], [1, 0, 0, 0]))
    assert position[0] == 0.0 and orientation[0] == math.inf  # no rotation at all


def test_summarise_headroom_on_a_known_answer():
    distances, positions, orientations, centres = constructed_queries()
    picks = [pick(*q) for q in zip(distances, positions, orientations, centres, strict=True)]
    assert [(p.centre, p.min_distance, p.oracle_position, p.oracle_orientation) for p in picks] == [
        (2, 1, 3, 4),
        (1, 0, 2, 1),
        (1, 1, 1, 2),
    ]
    summary = summarise_headroom(distances, positions, orientations, centres)
    errors = summary["errors"]
    assert errors["centre"]["median_position_m"] == pytest.approx(0.4)
    assert errors["centre"]["mean_position_m"] == pytest.approx(1.0 / 3)
    assert errors["centre"]["median_orientation_deg"] == pytest.approx(3.0)
    assert errors["min_distance"]["median_position_m"] == pytest.approx(0.3)
    assert errors["min_distance"]["mean_position_m"] == math.inf  # the NaN pose
    assert errors["oracle_position"]["median_position_m"] == pytest.approx(0.2)
    assert errors["oracle_position"]["mean_orientation_deg"] == pytest.approx(24.0 / 3)
    assert errors["oracle_orientation"]["mean_orientation_deg"] == pytest.approx(4.0)
    assert errors["oracle_orientation"]["median_position_m"] == pytest.approx(0.4)
    versus = summary["min_distance_vs_centre"]
    assert versus["share_better_position"] == pytest.approx(1 / 3)  # query 0 only
    assert versus["share_worse_position"] == pytest.approx(1 / 3)  # query 1: inf
    assert versus["wilcoxon_pairs"] == 2  # query 2 ties: same window
    assert 0.0 < versus["wilcoxon_p_position"] <= 1.0
    within = summary["spearman_within"]
    assert within["median"] == pytest.approx(0.6)  # 0.6, -1 (inf ranks last), 1
    assert within["share_positive"] == pytest.approx(2 / 3)
    assert within["queries"] == 3
    assert summary["spearman_across"] == pytest.approx(0.5)
    assert summary["queries"] == 3
    assert json_ready(summary)["errors"]["min_distance"]["mean_position_m"] == "inf"


def test_spearman_is_undefined_not_zero_for_a_constant_side():
    assert math.isnan(spearman([1.0, 1.0, 1.0], [0.1, 0.2, 0.3]))
    assert math.isnan(spearman([1.0], [0.1]))
    assert spearman([1.0, 2.0, 3.0], [0.3, 0.2, 0.1]) == pytest.approx(-1.0)


def test_every_offset_scored_once_on_the_pipelines_windows(tiny_scene):
    train_frames = load_sevenscenes(tiny_scene, None, "train")
    test_frames = load_sevenscenes(tiny_scene, None, "test")
    train, test = read_images(train_frames, quiet=True), read_images(test_frames, quiet=True)
    backbone = CountingPoseNet()
    # 1.05: the network sees the crop's centre, and the 34-pixel strip is smaller than
    # the image, so some offsets round to the same window.
    backbone.set_crop_scale(1.05)
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), SweepCrop(), QueryOptions(batch_size=5))
    relocalizer.fit(train)
    backbone.batches.clear()
    queries = diagnose(relocalizer, test_frames, test)
    # Never a window twice, never more than batch_size per forward pass.
    assert sum(backbone.batches) == sum(q.windows for q in queries)
    assert [q.windows for q in queries] == [len(np.unique(q.views, axis=0)) for q in queries]
    assert max(backbone.batches) <= 5
    centre = Relocalizer(backbone, relocalizer.index, CentreCrop())
    for frame, image, query, chosen in zip(
        test_frames, test, queries, picks_of(queries), strict=True
    ):
        span = 48 - 36  # 48x36 images: the square slides 12 pixels
        assert len(query.distances) == span + 1 == len(query.crops)
        assert 1 < query.windows < span + 1  # offsets 13, windows fewer: shared
        assert query.crops[0].tolist() == [0, 0, 36] and query.crops[-1].tolist() == [12, 0, 36]
        position, orientation = query.position_errors, query.orientation_errors
        oracle = chosen.oracle_position
        assert position[oracle] <= position[chosen.centre]
        assert position[oracle] <= position[chosen.min_distance]
        assert position[oracle] == position.min()
        assert orientation[chosen.oracle_orientation] == orientation.min()
        # The min-distance window is the one crop=sweep answers with.
        swept = relocalizer.localize(image)
        assert tuple(query.crops[chosen.min_distance]) == (swept.crop.x, swept.crop.y, 36)
        assert query.distances[chosen.min_distance] == pytest.approx(swept.distance)
        truth = frame.pose
        assert position[chosen.min_distance] == pytest.approx(
            position_error(swept.pose.position, truth.position)
        )
        # The centre entry is crop=centre's window and pose.
        answer = centre.localize(image)
        assert tuple(query.crops[query.centre]) == (answer.crop.x, answer.crop.y, 36)
        assert position[query.centre] == pytest.approx(
            position_error(answer.pose.position, truth.position)
        )
        assert orientation[query.centre] == pytest.approx(
            orientation_error_deg(answer.pose.quaternion, truth.quaternion), abs=1e-4
        )
        # crop_scale > 1: the network sees a centred square smaller than the crop.
        view = query.views[query.centre]
        assert view[2] < 36 and view[0] > query.crops[query.centre][0]


def test_cli_diagnose_writes_table_windows_and_figures(tmp_path):
    run_dir = tmp_path / "diagnose"
    args = [*TINY_OVERRIDES, "task=diagnose", "diagnose.curve_queries=2"]
    result = relocfw([*args, f"hydra.run.dir={run_dir}"], tmp_path)
    assert result.returncode == 0, result.stderr
    assert "| min map distance |" in result.stdout and "oracle (position)" in result.stdout
    report = json.loads((run_dir / "diagnose.json").read_text())
    summary = report["scenes"]["synthetic"]
    assert summary["queries"] == 4 and summary["mean_offsets_per_query"] == 13
    assert set(summary["errors"]) == {
        "centre",
        "min_distance",
        "oracle_position",
        "oracle_orientation",
    }
    assert report["settings"]["crop_scale"] == pytest.approx(1.142857, abs=1e-6)
    assert report["settings"]["scene"] == "synthetic"  # no dataset.scene: the dataset's name
    assert report["settings"]["query_batch_size"] == 16  # query.batch_size=null: the default
    assert (run_dir / "diagnose.md").read_text() in result.stdout
    # The map's and the queries' sequences and the poses they are scored against.
    split = report["split"]
    assert (split["train_sequences"], split["test_sequences"]) == ([1, 2], [3])
    assert split["pose_reference"]["kind"] == "dataset poses"
    assert "Sequences: map 1, 2; test 3; poses: dataset poses (" in result.stdout
    with open(run_dir / "diagnose_windows.csv") as stream:
        rows = list(csv.DictReader(stream))
    assert len(rows) == 4 * 13
    for frame in {r["frame"] for r in rows}:
        mine = [r for r in rows if r["frame"] == frame]
        for flag in ("is_centre", "is_min_distance", "is_oracle", "is_oracle_orientation"):
            assert sum(int(r[flag]) for r in mine) == 1, flag
        oracle = next(float(r["position_error_m"]) for r in mine if r["is_oracle"] == "1")
        assert oracle == min(float(r["position_error_m"]) for r in mine)
    # The recording: every window's pose, its nearest map images, the truth; the
    # errors it implies are the CSV's.
    recorded = load_windows(run_dir / "diagnose_windows.npz")
    assert [q.frame for q in recorded] == sorted(
        {r["frame"] for r in rows}, key=[r["frame"] for r in rows].index
    )
    for query in recorded:
        mine = [r for r in rows if r["frame"] == query.frame]
        position, _ = query.window_errors()
        assert query.windows.neighbour_positions.shape == (query.windows.count, 5, 3)
        written = np.array([float(r["position_error_m"]) for r in mine])
        gaps = np.abs(position[:, None] - written[None, :])  # CSV rounds to 1e-6
        assert gaps.min(axis=1).max() < 2e-6 and gaps.min(axis=0).max() < 2e-6
        centre_row = next(r for r in mine if r["is_centre"] == "1")
        assert position[query.windows.centre] == pytest.approx(
            float(centre_row["position_error_m"]), abs=1e-5
        )
    assert (run_dir / "training_curve.png").is_file()
    pngs = sorted(p.name for p in run_dir.glob("diagnose_*.png"))
    assert pngs == [
        "diagnose_crops.png",
        "diagnose_distance_vs_error.png",
        "diagnose_offset_curves.png",
    ]

    bad = relocfw_here([*TINY_OVERRIDES, "task=diagnose", "diagnose.table3_queries=-1"], tmp_path)
    assert bad.returncode == 2
    assert "diagnose.table3_queries must be at least 0, got -1" in bad.stderr
    assert "Traceback" not in bad.stderr


def test_within_query_correlation_counts_each_distinct_window_once():
    from scipy.stats import spearmanr

    from relocfw.report.diagnosis import distinct_windows

    # Three windows; the first is shared by four offsets (as at 96 px, where 161 offsets
    # land on 38 windows). Ranked once each: rho(d, e) = -0.5.
    distances = np.array([1.0, 1.0, 1.0, 1.0, 2.0, 3.0])
    errors = np.array([0.5, 0.5, 0.5, 0.5, 0.1, 0.2])
    d, e = distinct_windows(distances, errors)
    assert d.tolist() == [1.0, 2.0, 3.0] and spearman(d, e) == pytest.approx(-0.5)
    summary = summarise_headroom([distances], [errors], [np.zeros(6)], [0])
    assert summary["spearman_within"]["median"] == pytest.approx(-0.5)
    # Counted per offset, the shared window would weigh four times:
    assert spearmanr(distances, errors)[0] != pytest.approx(-0.5)
