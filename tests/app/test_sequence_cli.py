"""refine=sequence end to end: the sequence rows of task=compare on one model."""

import csv
import json
import shutil

import numpy as np

from relocfw import load_model
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.plugins.sequence_refiner import SequenceRefiner
from tests.cli_runs import relocfw
from tests.conftest import TINY_MODEL, TINY_OVERRIDES

# A short training: the test is about the rows' plumbing, not the LSTM's accuracy.
OPTIONS = (
    "crop=centre",
    "refine=sequence",
    "refine.window=3",
    "refine.steps=20",
    "refine.hidden=8",
)
SEQUENCE = ",".join(f'"{option}"' for option in OPTIONS)


def test_compare_runs_the_sequence_rows_on_posenets_model(tmp_path):
    run_dir = tmp_path / "compare"
    args = [
        *TINY_OVERRIDES,
        "task=compare",
        "compare.crop_seeds=null",
        "~compare.methods",
        '+compare.methods={PoseNet:["crop=centre"],'
        f'Causal:[{SEQUENCE}],Bidirectional:[{SEQUENCE},"refine.direction=bidirectional"]}}',
    ]
    result = relocfw([*args, f"hydra.run.dir={run_dir}"], tmp_path)
    assert result.returncode == 0, result.stderr
    # The LSTM reads the trained network's descriptors: one network for every row.
    assert result.stdout.count("(trained)") == 1
    summary = json.loads((run_dir / "summary_synthetic.json").read_text())
    rows = {row["method"]: row for row in summary}
    assert set(rows) == {"PoseNet", "Causal", "Bidirectional", "mean training pose"}
    centre = rows["PoseNet"]["median_position_m"]
    for name, row in rows.items():
        if name in ("Causal", "Bidirectional"):  # its own answer, from the frames of the recording
            assert row["median_position_m"] != centre, name
    answers = answers_of(run_dir / "results_synthetic.csv")
    # The refiner replaces the pose only: each query's crop and map distance are the
    # centre crop's of the same network, PoseNet's row's, to the digit.
    for name in ("Causal", "Bidirectional"):
        assert [a["window"] for a in answers[name]] == [a["window"] for a in answers["PoseNet"]]
    # Each row answers as task=relocalize does with the row's options (on the cached
    # network, no training): every option of the row reaches its refiner.
    sweep = tmp_path / "relocalized"
    again = relocfw(
        ["-m", *TINY_OVERRIDES, *OPTIONS, "refine.direction=causal,bidirectional"]
        + [f"hydra.sweep.dir={sweep}"],
        tmp_path,
    )
    assert again.returncode == 0, again.stderr
    assert "(trained)" not in again.stdout
    for job, name in enumerate(("Causal", "Bidirectional")):
        relocalized = answers_of(sweep / str(job) / "results.csv")
        (method,) = [m for m in relocalized if m.endswith("+ sequence")]
        assert relocalized[method] == answers[name], name


def answers_of(path):
    """results CSV -> method -> its rows in order: frame, estimated pose (the CSV's
    digits) and its window (crop and map distance)."""
    answers = {}
    with open(path) as stream:
        for row in csv.DictReader(stream):
            answers.setdefault(row["method"], []).append(
                {
                    "frame": row["frame"],
                    "pose": [row[f"est_{c}"] for c in ("x", "y", "z", "qw", "qx", "qy", "qz")],
                    "window": [row[c] for c in ("crop_x", "crop_y", "crop_size", "distance")],
                }
            )
    return answers


def test_a_sequence_model_file_localizes_a_folder_as_the_run_did(tiny_scene, tmp_path):
    """relocalize with refine=sequence stores the LSTM in the model file; task=localize
    on one recording's images (its folder: the recording) answers as the run did."""
    root = tmp_path / "data"
    shutil.copytree(tiny_scene, root / "room")
    run_dir = tmp_path / "run"
    args = [*TINY_MODEL, "dataset=sevenscenes", f"dataset.root={root}", "dataset.scene=room"]
    args += list(OPTIONS)
    result = relocfw([*args, f"hydra.run.dir={run_dir}"], tmp_path)
    assert result.returncode == 0, result.stderr
    loaded = load_model(run_dir / "model.relocfw")
    assert isinstance(loaded.refiner, SequenceRefiner)
    assert (loaded.refiner.window, loaded.refiner.hidden) == (3, 8)
    frames = load_sevenscenes(root / "room", None, "test")
    recording = frames[0].name.split("/")[0]
    with open(run_dir / "results.csv") as stream:
        rows = [
            r
            for r in csv.DictReader(stream)
            if "sequence" in r["method"] and r["frame"].startswith(f"{recording}/")
        ]
    assert len(rows) > 1
    out = tmp_path / "localized"
    images = f"localize.images={root / 'room' / recording}/*.color.png"
    result = relocfw(
        ["task=localize", f"localize.model={run_dir / 'model.relocfw'}", images, "quiet=true"]
        + [f"hydra.run.dir={out}"],
        tmp_path,
    )
    assert result.returncode == 0, result.stderr
    poses = [line.split() for line in (out / "poses.txt").read_text().splitlines()[1:]]
    assert len(poses) == len(rows)
    for written, pose in zip(rows, poses, strict=True):
        expected = [float(written[f"est_{axis}"]) for axis in "xyz"]
        np.testing.assert_allclose([float(v) for v in pose[1:4]], expected, atol=1e-5)
