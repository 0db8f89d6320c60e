"""Every results file records its map, validation and test sequences and the poses it
scored against (relocfw.app.split_record); task=compare refuses a run marked as
validation (compare.validation_for) whose sequences touch the test sequences."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from relocfw.app.split_record import check_validation_run, split_line, split_record
from relocfw.core.errors import ConfigError
from relocfw.core.values import Pose
from relocfw.data.frames import Frame
from relocfw.data.sevenscenes import SevenScenes, load_sevenscenes
from relocfw.report.calibration import Calibration
from tests.cli_runs import relocfw, relocfw_here
from tests.conftest import TINY_MODEL
from tests.data.test_pseudo_ground_truth import pgt_line

REDKITCHEN = Path(__file__).resolve().parents[3] / "shared" / "data" / "7scenes-redkitchen"
SFM = REDKITCHEN / "pgt" / "redkitchen_sfm.txt"
ONE_ROW = ["~compare.methods", '+compare.methods={PoseNet:["crop=centre"]}']


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("split-cache")


@pytest.fixture
def room(tiny_scene, tmp_path) -> list[str]:
    """The tiny scene as a 7-Scenes dataset (sequences 1 and 2 map, 3 is the test)."""
    shutil.copytree(tiny_scene, tmp_path / "data" / "room")
    return ["dataset=sevenscenes", f"dataset.root={tmp_path / 'data'}", "dataset.scene=room"]


def compare_args(room: list[str], run_dir: Path, *extra: str) -> list[str]:
    return [*TINY_MODEL, *room, "task=compare", *ONE_ROW, "compare.crop_seeds=null"] + [
        *extra,
        f"hydra.run.dir={run_dir}",
    ]


def test_a_validation_run_records_its_queries_as_validation(room, tmp_path, cache):
    run_dir = tmp_path / "compare"
    args = compare_args(
        room,
        run_dir,
        "dataset.train_sequences=[1]",
        "dataset.test_sequences=[2]",
        "compare.validation_for=[3]",
    )
    result = relocfw_here(args, tmp_path, cache)
    assert result.returncode == 0, result.stderr
    scene = tmp_path / "data" / "room"
    expected = {
        "train_sequences": [1],
        "train_source": f"dataset.train_sequences=[1] in {scene}",
        "validation": {
            "query_sequences": [2],
            "query_source": f"dataset.test_sequences=[2] in {scene}",
        },
        "test_sequences": [3],
        "test_source": "compare.validation_for=[3]",
        "pose_reference": {
            "kind": "dataset poses",
            "file": f"{scene}/seq-NN/frame-NNNNNN.pose.txt",
            "sha256": None,
            "poses_of": "colour",
        },
    }
    line = (
        "Sequences: map 1; validation queries 2 (choosing settings for test 3); poses: "
        f"dataset poses ({scene}/seq-NN/frame-NNNNNN.pose.txt)."
    )
    report = json.loads((run_dir / "comparison.json").read_text())
    assert report["splits"] == {"room": expected}
    assert report["reference"] == "PoseNet"  # the reference row keeps its key
    assert line in (run_dir / "comparison.md").read_text().splitlines()
    rows = json.loads((run_dir / "summary_room.json").read_text())
    assert [row["split"] for row in rows] == [expected] * 2
    assert line in result.stdout


def test_the_comparison_over_seeds_records_each_scenes_split(tmp_path):
    """compare.seeds: the top-level comparison.json / .md and each seed's say the
    sequences of every scene, one line per scene where there are several."""
    from relocfw.app.tasks.compare import write_comparison, write_seed_comparison
    from tests.report.test_seed_comparison import answered

    results = {
        seed: {scene: {"Ref": answered("Ref", [0.1, 0.2, 0.3])} for scene in ("a", "b")}
        for seed in (0, 1)
    }
    floor = answered("mean training pose", [1.0] * 3)
    splits = {
        scene: {
            "train_sequences": [1, 3],
            "train_source": "TrainSplit.txt",
            "validation": None,
            "test_sequences": [number],
            "test_source": "TestSplit.txt",
            "pose_reference": {"kind": "dataset poses", "file": None, "sha256": None},
        }
        for scene, number in (("a", 2), ("b", 4))
    }
    for seed in (0, 1):
        folder = tmp_path / f"seed_{seed}"
        write_comparison(
            results[seed], {"a": floor.frames, "b": floor.frames}, {}, "Ref", folder, splits=splits
        )
    write_seed_comparison(results, {"a": floor, "b": floor}, "Ref", tmp_path, splits=splits)
    for folder in (tmp_path, tmp_path / "seed_0", tmp_path / "seed_1"):
        assert json.loads((folder / "comparison.json").read_text())["splits"] == splits
        lines = (folder / "comparison.md").read_text().splitlines()
        assert lines[:2] == [
            "Sequences (a): map 1, 3; test 2; poses: dataset poses.",
            "Sequences (b): map 1, 3; test 4; poses: dataset poses.",
        ], folder
    summary = json.loads((tmp_path / "seed_0" / "summary_b.json").read_text())
    assert [row["split"] for row in summary] == [splits["b"]] * 2


def test_a_validation_run_touching_its_test_sequences_is_refused(room, tmp_path, cache):
    """The near split's map touches the sequences validation_for tests on: refused in one
    line naming them and the option that listed them, before any training."""
    run_dir = tmp_path / "compare"
    args = compare_args(room, run_dir, "dataset.test_sequences=[3]", "compare.validation_for=[2]")
    result = relocfw(args, tmp_path, cache)
    assert result.returncode == 2
    scene = tmp_path / "data" / "room"
    assert result.stderr.strip() == (
        "error: compare.validation_for=[2] marks a validation run, but its map uses 2 "
        f"({scene / 'TrainSplit.txt'}): validation must not touch the test sequences it "
        "chooses settings for"
    )
    assert "(trained)" not in result.stdout and not (run_dir / "comparison.json").exists()


@pytest.mark.parametrize(
    "extra, message",
    [
        (
            [
                "dataset.train_sequences=[1]",
                "dataset.test_sequences=[2]",
                "compare.validation_for=[1,2,3]",
            ],
            "its map uses 1 (dataset.train_sequences=[1] in {scene}) and its queries use 2 "
            "(dataset.test_sequences=[2] in {scene})",
        ),
        (["compare.validation_for=[3]"], "its queries use 3 ({scene}/TestSplit.txt)"),
        (["compare.validation_for=x"], "compare.validation_for must be a list"),
        (["compare.validation_for=[]"], "compare.validation_for must be a list"),
        (["compare.validation_for=[0]"], "integers >= 1, got 0"),
        (["compare.validation_for=[3,3]"], "lists a sequence twice: [3, 3]"),
    ],
)
def test_validation_for_refusals_name_the_sequences(room, tmp_path, extra, message):
    result = relocfw_here(compare_args(room, tmp_path / "run", *extra), tmp_path)
    assert result.returncode == 2, result.stderr
    assert message.format(scene=tmp_path / "data" / "room") in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr


def folder_frames(tmp_path: Path) -> list[Frame]:
    """Frames named as a folder of images names them: no sequence numbers."""
    pose = Pose(np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
    return [Frame(f"images/{i:03d}.png", tmp_path / f"{i:03d}.png", pose) for i in range(3)]


def test_validation_for_needs_numbered_sequences(tmp_path):
    """A dataset without sequence numbers (a folder of images with a poses file) cannot
    be checked against sequence numbers: refused, not silently accepted."""
    frames = folder_frames(tmp_path)
    with pytest.raises(ConfigError, match="not numbered sequences"):
        check_validation_run(object(), frames, frames, [5])


def test_a_run_against_a_pgt_file_records_it_with_its_hash(tiny_scene, tmp_path):
    """task=relocalize scored against a pseudo-ground-truth file: summary.json names the
    file, its sha256 and the sequences."""
    scene = tmp_path / "room"
    shutil.copytree(tiny_scene, scene)
    frames = load_sevenscenes(scene, None, "train", sequences=[1, 2, 3])
    pgt = tmp_path / "pgt.txt"
    pgt.write_text("".join(pgt_line(f"{f.name}.color.png", f.pose, 30) + "\n" for f in frames))
    run_dir = tmp_path / "run"
    args = ["dataset=sevenscenes", f"dataset.root={scene}", "dataset.scene=null", *TINY_MODEL]
    result = relocfw_here([*args, f"dataset.pgt={pgt}", f"hydra.run.dir={run_dir}"], tmp_path)
    assert result.returncode == 0, result.stderr
    rows = json.loads((run_dir / "summary.json").read_text())
    sha = hashlib.sha256(pgt.read_bytes()).hexdigest()
    for row in rows:
        assert row["split"] == {
            "train_sequences": [1, 2],
            "train_source": str(scene / "TrainSplit.txt"),
            "validation": None,
            "test_sequences": [3],
            "test_source": str(scene / "TestSplit.txt"),
            "pose_reference": {"kind": "pgt", "file": str(pgt), "sha256": sha},
        }
    assert split_line(rows[0]["split"]) == (
        f"Sequences: map 1, 2; test 3; poses: pgt pgt.txt (sha256 {sha[:12]})."
    )


def test_the_calibration_block_is_recorded_as_validation(tiny_scene):
    dataset = SevenScenes(str(tiny_scene), None)
    train, test = dataset.frames("train"), dataset.frames("test")
    block = Calibration(train[-5:], [None] * 5)
    record = split_record(dataset, train[:-5], test, block)
    assert record["validation"] == {
        "calibration_block": {
            "frames": 5,
            "first": "seq-02/frame-000003",
            "last": "seq-02/frame-000007",
            "sequences": [2],
        }
    }
    assert record["train_sequences"] == [1, 2] and record["test_sequences"] == [3]
    assert "calibration block seq-02/frame-000003 .. seq-02/frame-000007 (5 frames)" in (
        split_line(record)
    )


@pytest.fixture
def redkitchen() -> Path:
    if not SFM.is_file() or not (REDKITCHEN / "redkitchen" / "TrainSplit.txt").is_file():
        pytest.skip(f"Red Kitchen frames or their pgt/ files not found at {REDKITCHEN}")
    return REDKITCHEN


def test_settings_for_the_far_split_cannot_be_chosen_on_the_near_split(redkitchen):
    """Red Kitchen's near split maps 1, 3, 5, 7 and tests 2, 4, 6: a run on it marked
    as choosing settings for the far split (tested on 5, 6, 7) is refused, naming the
    sequences of each; the far split's own training blocks 1-4 pass."""
    near = SevenScenes(str(redkitchen), "redkitchen", pgt=str(SFM))
    train, test = near.frames("train"), near.frames("test")
    folder = redkitchen / "redkitchen"
    with pytest.raises(ConfigError) as refused:
        check_validation_run(near, train, test, [5, 6, 7])
    assert str(refused.value) == (
        f"compare.validation_for=[5, 6, 7] marks a validation run, but its map uses 5, 7 "
        f"({folder / 'TrainSplit.txt'}) and its queries use 6 ({folder / 'TestSplit.txt'}): "
        "validation must not touch the test sequences it chooses settings for"
    )
    clean = SevenScenes(
        str(redkitchen), "redkitchen", train_sequences=[1, 3], test_sequences=[2, 4]
    )
    train, test = clean.frames("train"), clean.frames("test")
    check_validation_run(clean, train, test, [5, 6, 7])
    record = split_record(clean, train, test, None, [5, 6, 7])
    assert (record["train_sequences"], record["test_sequences"]) == ([1, 3], [5, 6, 7])
    assert record["validation"]["query_sequences"] == [2, 4]
    assert record["pose_reference"]["file"] == f"{folder}/seq-NN/frame-NNNNNN.pose.txt"
    # The near split under SfM names the published file by its hash.
    record = split_record(near, near.frames("train"), near.frames("test"))
    assert record["pose_reference"]["sha256"] == hashlib.sha256(SFM.read_bytes()).hexdigest()
    assert (record["train_sequences"], record["test_sequences"]) == ([1, 3, 5, 7], [2, 4, 6])
