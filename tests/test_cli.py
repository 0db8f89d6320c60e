"""The `relocfw` command end to end, on a tiny configuration, in a subprocess."""

import csv
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import TINY_MODEL, TINY_OVERRIDES


def relocfw(args, tmp_path, cache=None, **env_extra):
    """Run the CLI in a subprocess, as a user would."""
    env = {**os.environ, "RELOCFW_CACHE": str(cache or tmp_path / "cache"), **env_extra}
    return subprocess.run(
        [sys.executable, "-m", "relocfw", *args],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("cli-cache")


def test_main_job_writes_results_and_reuses_the_model(tmp_path, cache):
    run_dir = tmp_path / "run"
    args = [*TINY_OVERRIDES, "train.log=tensorboard", f"hydra.run.dir={run_dir}"]
    result = relocfw(args, tmp_path, cache)
    assert result.returncode == 0, result.stderr
    for row in ("mean training pose", "posenet (centre crop)", "ga + kmeans (k=4)"):
        assert row in result.stdout
    assert (run_dir / "training_curve.png").is_file()
    assert list((run_dir / "tensorboard").glob("events.out.tfevents.*"))
    summary = json.loads((run_dir / "summary.json").read_text())
    assert [s["method"] for s in summary][-1] == "ga + kmeans (k=4)"
    assert all(s["queries"] == 4 for s in summary)
    with open(run_dir / "results.csv") as stream:
        rows = list(csv.DictReader(stream))
    assert len(rows) == 3 * 4
    assert {r["frame"] for r in rows} == {f"seq-03/frame-00000{i}" for i in range(4)}
    checkpoints = list((cache / "checkpoints").glob("*.pt"))
    assert len(checkpoints) == 1
    stamp = checkpoints[0].stat().st_mtime_ns

    # A second method on the same model: the checkpoint is reused, not retrained.
    again = relocfw(
        [*TINY_OVERRIDES, "crop=sweep", "index=exhaustive", f"hydra.run.dir={tmp_path / 'r2'}"],
        tmp_path,
        cache,
    )
    assert again.returncode == 0, again.stderr
    assert "sweep + exhaustive" in again.stdout
    assert "(reused)" in again.stdout and "(trained)" in result.stdout
    assert (tmp_path / "r2" / "training_curve.png").is_file()  # drawn from the checkpoint
    assert checkpoints[0].stat().st_mtime_ns == stamp
    assert len(list((cache / "checkpoints").glob("*.pt"))) == 1


def test_train_task_and_multirun(tmp_path, cache):
    trained = relocfw([*TINY_OVERRIDES, "task=train"], tmp_path, cache)
    assert trained.returncode == 0, trained.stderr
    assert "model:" in trained.stdout and "mean training pose" not in trained.stdout
    multi = relocfw(
        ["-m", "crop=centre,sweep", *TINY_OVERRIDES, f"hydra.sweep.dir={tmp_path / 'multi'}"],
        tmp_path,
        cache,
    )
    assert multi.returncode == 0, multi.stderr
    assert (tmp_path / "multi" / "0" / "summary.json").is_file()
    assert (tmp_path / "multi" / "1" / "summary.json").is_file()


def test_compare_writes_table_and_five_figures(tmp_path, cache):
    run_dir = tmp_path / "compare"
    result = relocfw([*TINY_OVERRIDES, "task=compare", f"hydra.run.dir={run_dir}"], tmp_path, cache)
    assert result.returncode == 0, result.stderr
    # Seven methods, one trained model.
    assert result.stdout.count("(trained)") <= 1 and result.stdout.count("(reused)") >= 6
    header = (run_dir / "comparison.csv").read_text().splitlines()[0]
    methods = ("PoseNet", "Bayesian PoseNet", "Retrieval", "Ours (GA + k-means)")
    for method in (*methods, "Ours, shared scoring", "Sweep + k-means", "GA + exhaustive"):
        assert method in header
    assert "Sweep + exhaustive" not in header  # changed search AND index: bounds nothing
    assert "Bayesian PoseNet uncertainty" in result.stdout
    # Every row shares one trained model: one training curve.
    assert len(list(run_dir.glob("training_curve_*.png"))) == 1
    pngs = sorted(p.name for p in run_dir.glob("synthetic_*.png"))
    assert pngs == [
        "synthetic_Bayesian_PoseNet_uncertainty.png",
        "synthetic_error_per_image.png",
        "synthetic_orientation_error_histogram.png",
        "synthetic_position_error_histogram.png",
        "synthetic_trajectory_top_down.png",
        "synthetic_tsne_kmeans_map.png",
    ]
    summary = json.loads((run_dir / "comparison.json").read_text())
    assert "Bayesian PoseNet" in summary["scenes"]["synthetic"]["uncertainty"]
    quality = summary["scenes"]["synthetic"]["uncertainty"]["Bayesian PoseNet"]["quality"]
    assert set(quality) == {"position", "orientation"} and "ause" in quality["position"]
    assert "Bayesian PoseNet uncertainty quality" in result.stdout
    # The GA methods ran once per crop seed; the deterministic ones did not.
    spread = summary["scenes"]["synthetic"]["crop_seed_spread"]
    assert sorted(spread) == ["GA + exhaustive", "Ours (GA + k-means)", "Ours, shared scoring"]
    assert spread["Ours (GA + k-means)"]["seeds"] == [0, 1, 2]
    assert len(spread["Ours (GA + k-means)"]["median_position_m"]) == 3
    assert "Ours (GA + k-means)" in (run_dir / "crop_seeds.md").read_text()


def test_compare_of_the_dropout_variants(tmp_path, cache):
    run_dir = tmp_path / "compare"
    args = [*TINY_OVERRIDES, "task=compare", "methods=bayesian", "compare.crop_seeds=null"]
    result = relocfw([*args, f"hydra.run.dir={run_dir}"], tmp_path, cache)
    assert result.returncode == 0, result.stderr
    # Three models: PoseNet's (head dropout), and kendall's and all's, which drop in
    # training too; the other rows reuse them.
    assert result.stdout.count("(trained)") <= 3 and result.stdout.count("(reused)") >= 3
    summary = json.loads((run_dir / "comparison.json").read_text())
    uncertainty = summary["scenes"]["synthetic"]["uncertainty"]
    assert sorted(uncertainty) == [
        "Bayesian PoseNet (all)",
        "Bayesian PoseNet (head)",
        "Bayesian PoseNet (kendall)",
        "Crop sampling",
        "Crop sampling + MC (kendall)",
        "Ours + MC dropout (kendall)",
    ]
    for quality in (u["quality"] for u in uncertainty.values()):
        assert "ause" in quality["position"] and "ause" in quality["orientation"]
    assert (run_dir / "synthetic_Bayesian_PoseNet__kendall__uncertainty.png").is_file()


@pytest.mark.parametrize(
    "args, message",
    [
        (["crop=nosuch"], "Could not find 'crop/nosuch'"),
        (["k=0"], "k must be at least 1, got 0"),
        (["k=500"], "k=500 is more clusters than training descriptors"),
        (["crop.population=1"], "population must be at least 2"),
        (["dataset=sevenscenes", "dataset.root=/no/such/dir"], "/no/such/dir"),
        (["train.optimizer=rmsprop"], "train.optimizer"),
        (["train.log=wandb"], "train.log must be none or tensorboard"),
        (["crop_samples=4", "train.crop_scale=1.0"], "the window fills the crop"),
        (["rerank=3"], "with scoring=plain every candidate is already plain"),
        (["queries_at_once=0"], "queries_at_once must be at least 1"),
        (["task=nosuch"], "task must be one of"),
        (["device=cuda:7"], "device"),
        (["task=compare", "compare.reference=Nobody"], "compare.reference"),
        (["retrieval_k=1"], "needs an index that returns neighbours"),
        (["scoring=fast"], "scoring must be one of plain, shared, got 'fast'"),
        (["index=faiss", "index.kind=lsh"], "index.kind must be one of flat, ivf, hnsw"),
        (["index=faiss", "index.kind=ivf"], "nlist=1024 is more IVF cells than map"),
        (["preset=paper"], "preset=paper fine-tunes ImageNet weights (train.lr=1e-05)"),
        (["backbone=bayesian_posenet", "preset=paper"], "or a pretrained backbone"),
        (["train.crop_scale=0.5"], "train.crop_scale must be in [1, 4]"),
    ],
)
def test_bad_options_end_in_one_clear_message(tmp_path, cache, args, message):
    tiny = TINY_MODEL if "dataset=sevenscenes" in args else TINY_OVERRIDES
    result = relocfw([*tiny, *args], tmp_path, cache)
    assert result.returncode != 0
    assert message in result.stderr
    assert "Traceback" not in result.stderr
    assert "model:" not in result.stdout  # refused before any training


def test_the_centre_crop_row_says_when_it_samples_dropout(tmp_path, cache):
    run_dir = tmp_path / "run"
    args = [*TINY_OVERRIDES, "backbone.mc_samples=2", f"hydra.run.dir={run_dir}"]
    result = relocfw(args, tmp_path, cache)
    assert result.returncode == 0, result.stderr
    methods = [s["method"] for s in json.loads((run_dir / "summary.json").read_text())]
    assert methods[1] == "posenet x2 MC dropout (centre crop)"
    assert "posenet (centre crop)" not in result.stdout


def test_compare_rows_say_when_the_command_line_samples_dropout(tmp_path, cache):
    run_dir = tmp_path / "compare"
    methods = '+compare.methods={PoseNet:["crop=centre"],Bayes:["backbone.mc_samples=3"]}'
    args = [*TINY_OVERRIDES, "task=compare", "~compare.methods", methods]
    args += ["backbone.mc_samples=2", "crop=centre"]
    result = relocfw([*args, f"hydra.run.dir={run_dir}"], tmp_path, cache)
    assert result.returncode == 0, result.stderr
    header = (run_dir / "comparison.csv").read_text().splitlines()[0]
    # PoseNet did not ask for sampling but got it from the command line: it says so.
    assert "PoseNet (x2 MC dropout) (m, deg)" in header
    assert "Bayes (m, deg)" in header  # asked for its own samples: its name stands


def test_corrupt_image_names_the_file(tmp_path, cache, tiny_scene):
    root = tmp_path / "data"
    shutil.copytree(tiny_scene, root / "room")
    bad = root / "room" / "seq-01" / "frame-000004.color.png"
    bad.write_bytes(b"\x89PNG truncated")
    result = relocfw(
        [*TINY_MODEL, "dataset=sevenscenes", f"dataset.root={root}", "dataset.scene=room"],
        tmp_path,
        cache,
    )
    assert result.returncode == 2
    assert f"cannot decode image (corrupt or not an image): {bad}" in result.stderr


def test_help_lists_the_options_with_their_package(tmp_path):
    result = relocfw(["--help"], tmp_path)
    assert result.returncode == 0
    assert "crop (CropSearch):" in result.stdout and "index (SimilarityIndex):" in result.stdout
    for option in ("centre", "ga", "sweep", "exhaustive", "kmeans", "posenet", "tum"):
        assert re.search(rf"\n  {option}\s+\[relocfw\] ", result.stdout), option


def test_console_script_is_installed():
    script = Path(sys.executable).with_name("relocfw")
    assert script.is_file(), "pip install -e . should install the relocfw command"
