"""refine=features and refine=retrieval end to end: the structure rows of task=compare,
the retrieval refiner in a model file, and their refusals."""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest

from relocfw import load_model
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.plugins.retrieval_refiner import RetrievalRefiner
from tests.cli_runs import relocfw, relocfw_here, users_methods
from tests.conftest import TINY_MODEL
from tests.data.formats import write_folder

# A synthetic scene large enough for SIFT (160 x 120), still rendered in seconds.
SCENE = [
    "dataset.width=160",
    "dataset.height=120",
    "dataset.train_laps=2",
    "dataset.train_frames_per_lap=12",
    "dataset.test_frames=6",
]


def test_the_structure_rows_beat_an_untrained_network(tmp_path):
    pytest.importorskip("poselib")
    run_dir = tmp_path / "compare"
    args = [*TINY_MODEL, *SCENE, "task=compare", "methods=structure", "compare.crop_seeds=null"]
    result = relocfw([*args, f"hydra.run.dir={run_dir}"], tmp_path)
    assert result.returncode == 0, result.stderr
    header = (run_dir / "comparison.csv").read_text().splitlines()[0]
    rows = ("Structure (features + depth)", "Structure RGB-only", "PoseNet + features")
    for row in (*rows, "Relative pose (keyframes)"):
        assert row in header
    summary = {s["method"]: s for s in json.loads((run_dir / "summary_synthetic.json").read_text())}
    depth, network = summary["Structure (features + depth)"], summary["PoseNet"]
    # Three training steps: the network is lost; rendered depth + PnP is not.
    assert depth["median_position_m"] < 0.1 < network["median_position_m"]
    assert depth["refine_fell_back"] < 6 and "refine_median_ms_solve" in depth
    assert "refine_fell_back" not in network
    relative = summary["Relative pose (keyframes)"]
    assert "refine_fell_back" in relative and "refine_median_ms_solve" in relative
    # The structure is built once per kind (depth, triangulated, refine=relative's
    # keyframe features) and cached.
    assert len(list((tmp_path / "cache" / "structure").glob("*.npz"))) == 3


def test_a_dataset_without_cameras_is_refused_by_name(tiny_scene, tmp_path):
    pytest.importorskip("poselib")
    write_folder(tiny_scene, tmp_path / "folder")
    args = [*TINY_MODEL, "dataset=folder", f"dataset.root={tmp_path / 'folder'}"]
    result = relocfw_here([*args, "refine=features"], tmp_path)
    assert result.returncode == 2
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith("error: refine=features needs the camera intrinsics of every map")
    assert "has none" in line
    assert not (tmp_path / "cache" / "checkpoints").exists()  # refused before training


def test_map_images_without_depth_are_named_not_dropped(tiny_scene, tmp_path):
    pytest.importorskip("poselib")
    root = tmp_path / "data"
    shutil.copytree(tiny_scene, root / "room")
    (root / "room" / "seq-01" / "frame-000002.depth.png").unlink()
    args = [*TINY_MODEL, "dataset=sevenscenes", f"dataset.root={root}", "dataset.scene=room"]
    result = relocfw([*args, "refine=features", "crop=centre"], tmp_path)
    assert result.returncode == 0, result.stderr
    assert "1 of 16 map images give the refiner no 3-D point (first: seq-01/frame-000002" in (
        result.stderr
    )


def test_refine_retrieval_runs_with_k_means_and_is_stored_in_the_model_file(tiny_scene, tmp_path):
    """refine=retrieval beside index=kmeans (no exhaustive index needed), its k in the
    row's name, stored in the model file: the loaded model answers as the run did."""
    root = tmp_path / "data"
    shutil.copytree(tiny_scene, root / "room")
    run_dir = tmp_path / "run"
    args = [*TINY_MODEL, "dataset=sevenscenes", f"dataset.root={root}", "dataset.scene=room"]
    args += ["crop=centre", "index=kmeans", "refine=retrieval", "refine.k=2"]
    result = relocfw([*args, f"hydra.run.dir={run_dir}"], tmp_path)
    assert result.returncode == 0, result.stderr
    assert "cannot be stored in a model file" not in result.stdout
    summary = {s["method"]: s for s in json.loads((run_dir / "summary.json").read_text())}
    row = summary["retrieval of 2 nearest, centre crop"]
    # Never fallen back; its confidence is minus a descriptor distance.
    assert row["refine_fell_back"] == 0 and row["refine_median_confidence"] <= 0
    assert "posenet (centre crop)" in summary  # the network's own pose beside it
    loaded = load_model(run_dir / "model.relocfw")
    assert isinstance(loaded.refiner, RetrievalRefiner) and loaded.refiner.k == 2
    frames = load_sevenscenes(root / "room", None, "test")
    answers = loaded.localize_many(read_images(frames, quiet=True))
    with open(run_dir / "results.csv") as stream:
        rows = [
            r
            for r in csv.DictReader(stream)
            if r["method"] == "retrieval of 2 nearest, centre crop"
        ]
    assert [r["frame"] for r in rows] == [f.name for f in frames]
    for answer, written in zip(answers, rows, strict=True):
        position = [float(written[f"est_{axis}"]) for axis in "xyz"]
        assert np.allclose(answer.pose.position, position, atol=2e-6)


def test_structure_rows_take_turns_and_report_the_whole_query(tmp_path):
    pytest.importorskip("poselib")
    run_dir = tmp_path / "compare"
    rows = users_methods(
        tmp_path,
        "turns",
        "PoseNet: [crop=centre]\n"
        "Depth: [crop=centre, refine=features, refine.image_scale=1.0]\n"
        "Depth half: [crop=centre, refine=features, refine.image_scale=0.5]\n",
    )
    args = [*TINY_MODEL, *SCENE, "task=compare", *rows, "compare.crop_seeds=null"]
    result = relocfw([*args, "compare.round_robin=true", f"hydra.run.dir={run_dir}"], tmp_path)
    assert result.returncode == 0, result.stderr
    assert "synthetic: 3 methods take turns, query by query" in result.stdout
    summary = {s["method"]: s for s in json.loads((run_dir / "summary_synthetic.json").read_text())}
    assert summary["Depth"]["median_position_m"] < 0.1, summary["Depth"]
    for name in ("Depth", "Depth half"):
        row = summary[name]
        parts = [row[f"refine_median_ms_{p}"] for p in ("retrieval", "features", "matching")]
        assert 0 < row["median_ms_network"] < 1000 * row["median_seconds_per_query"]
        assert sum(parts) < 1000 * row["median_seconds_per_query"]
    bad = relocfw_here([*args, "compare.round_robin=yes"], tmp_path)
    assert bad.returncode != 0 and "compare.round_robin must be true or false" in bad.stderr


def test_round_robin_refuses_grouped_queries_before_training(tmp_path):
    args = [*TINY_MODEL, *SCENE, "task=compare", "methods=structure_core"]
    result = relocfw_here([*args, "compare.round_robin=true", "query.queries_at_once=4"], tmp_path)
    assert result.returncode == 2
    assert "compare.round_robin times one query at a time" in result.stderr
    assert not list((tmp_path / "cache").glob("checkpoints/*.pt"))  # nothing trained
