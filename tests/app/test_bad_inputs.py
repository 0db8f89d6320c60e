"""Bad input of every kind ends in one clear message naming the file or key, exit 2.

The cases run the command in this process (tests.cli_runs.relocfw_here); one of each
path also runs in a process of its own."""

import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from relocfw.app.devices import pick_device
from relocfw.core.atomic_files import LOCKED_GRACE_SECONDS
from relocfw.core.errors import ConfigError
from relocfw.model.checkpoints import load_checkpoint
from tests.cli_runs import relocfw, relocfw_here
from tests.conftest import TINY_MODEL, TINY_OVERRIDES
from tests.data.formats import write_cambridge, write_folder, write_tum


def replace_line(path, number, text):
    lines = path.read_text().splitlines()
    lines[number - 1] = text
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def datasets(tiny_scene, tmp_path_factory):
    root = tmp_path_factory.mktemp("formats")
    write_tum(tiny_scene, root / "tum")
    write_cambridge(tiny_scene, root / "cambridge")
    write_folder(tiny_scene, root / "folder")
    shutil.copytree(tiny_scene, root / "7scenes" / "room")
    return root


def tum(root):
    return [
        "dataset=tum",
        f"dataset.root={root}",
        "dataset.train=[lap1,lap2]",
        "dataset.test=[lap3]",
    ]


def damage(case, root):
    """Break a fresh copy of the datasets; return (dataset args, the message expected)."""
    t, c, f, s = root / "tum", root / "cambridge", root / "folder", root / "7scenes"
    cambridge = ["dataset=cambridge", f"dataset.root={c}", "dataset.scene=Room"]
    folder = ["dataset=folder", f"dataset.root={f}"]
    scenes = ["dataset=sevenscenes", f"dataset.root={s}", "dataset.scene=room"]
    gt = t / "lap1" / "groundtruth.txt"
    if case == "tum nan":
        replace_line(gt, 3, "1000.038333 1.0 nan 1.0 0 0 0 1")
        return tum(t), f"{gt}:3: NaN or infinite value"
    if case == "tum columns":
        replace_line(gt, 4, "1000.071667 1.0 2.0 1.0 0 0 1")
        return tum(t), f"{gt}:4: expected 8 values, found 7"
    if case == "tum duplicate timestamp":
        replace_line(gt, 3, gt.read_text().splitlines()[1])
        return tum(t), f"{gt}:3: duplicate timestamp"
    if case == "tum zero quaternion":
        replace_line(gt, 2, "1000.005 1 2 1 0 0 0 0")
        return tum(t), f"{gt}:2: quaternion has (near) zero norm"
    if case == "tum missing rgb.txt":
        (t / "lap3" / "rgb.txt").unlink()
        return tum(t), f"file not found: {t / 'lap3' / 'rgb.txt'}"
    if case == "tum missing lap":
        return tum(t)[:-1] + ["dataset.test=[lap9]"], f"sequence folder not found: {t / 'lap9'}"
    if case == "cambridge columns":
        path = c / "Room" / "dataset_train.txt"
        replace_line(path, 5, "seq1/frame.png 1 2 3")
        return cambridge, f"{path}:5: expected 'path x y z w p q r', found 4 values"
    if case == "cambridge text":
        path = c / "Room" / "dataset_test.txt"
        replace_line(path, 4, "seq2/a.png 1 2 3 one 0 0 0")
        return cambridge, f"{path}:4: not a number"
    if case == "cambridge missing split":
        (c / "Room" / "dataset_test.txt").unlink()
        return cambridge, f"file not found: {c / 'Room' / 'dataset_test.txt'}"
    if case == "folder missing column":
        path = f / "train.csv"
        replace_line(path, 1, "qz,qy,qx,qw,z,y,depth,image")
        return folder, f"{path}:1: header has no 'x' column"
    if case == "folder short row":
        path = f / "test.csv"
        replace_line(path, 3, "0,0,0,1,1,2,images/x.png")
        return folder, f"{path}:3: 7 values, the header names 8 columns"
    if case == "folder empty":
        (f / "test.csv").write_text("")
        return folder, f"{f / 'test.csv'}: empty poses file"
    if case == "folder missing image":
        path = f / "train.csv"
        first = path.read_text().splitlines()[1].split(",")
        replace_line(path, 2, ",".join(first[:-1] + ["images/nowhere.png"]))
        return folder, f"image not found: {f / 'images' / 'nowhere.png'}"
    if case == "7scenes non-rigid":
        path = s / "room" / "seq-02" / "frame-000001.pose.txt"
        path.write_text("1 0 0 0\n0 1 0.5 0\n0 0 1 0\n0 0 0 1\n")
        return scenes, f"{path}: not a rigid transform"
    if case == "7scenes truncated image":
        path = s / "room" / "seq-01" / "frame-000002.color.png"
        path.write_bytes(path.read_bytes()[:60])
        return scenes, f"cannot decode image (corrupt or not an image): {path}"
    if case == "7scenes empty split":
        (s / "room" / "TestSplit.txt").write_text("\n")
        return scenes, f"{s / 'room' / 'TestSplit.txt'}: lists no sequences"
    if case == "missing root":
        return [
            "dataset=folder",
            f"dataset.root={root / 'nowhere'}",
        ], "dataset.root: folder not found"
    raise AssertionError(case)


CASES = [
    "tum nan",
    "tum columns",
    "tum duplicate timestamp",
    "tum zero quaternion",
    "tum missing rgb.txt",
    "tum missing lap",
    "cambridge columns",
    "cambridge text",
    "cambridge missing split",
    "folder missing column",
    "folder short row",
    "folder empty",
    "folder missing image",
    "7scenes non-rigid",
    "7scenes truncated image",
    "7scenes empty split",
    "missing root",
]


@pytest.mark.parametrize("case", CASES)
def test_bad_dataset_input(case, datasets, tmp_path):
    root = tmp_path / "data"
    shutil.copytree(datasets, root)
    args, message = damage(case, root)
    result = relocfw_here([*TINY_MODEL, *args], tmp_path)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr
    assert result.stderr.count("error:") == 1 and "Traceback" not in result.stderr


def test_a_bad_dataset_ends_a_real_process_with_one_line(datasets, tmp_path):
    root = tmp_path / "data"
    shutil.copytree(datasets, root)
    args, message = damage("tum nan", root)
    result = relocfw([*TINY_MODEL, *args], tmp_path)
    assert result.returncode == 2
    assert result.stderr == f"error: {message}\n"


def test_skip_lists_what_it_left_out(datasets, tmp_path):
    root = tmp_path / "data"
    shutil.copytree(datasets, root)
    path = root / "folder" / "train.csv"
    replace_line(path, 3, "0,0,0,1,1,2,images/x.png")
    bad_image = root / "folder" / "images" / "train_005.png"
    bad_image.write_bytes(b"broken")
    run_dir = tmp_path / "run"
    result = relocfw(
        [
            *TINY_MODEL,
            "dataset=folder",
            f"dataset.root={root / 'folder'}",
            "dataset.on_error=skip",
            "task=train",
            f"hydra.run.dir={run_dir}",
        ],
        tmp_path,
    )
    assert result.returncode == 0, result.stderr
    skipped = (run_dir / "skipped.txt").read_text().splitlines()
    assert len(skipped) == 2
    assert f"{path}:3" in skipped[0] and str(bad_image) in skipped[1]
    assert "skipped 2 bad entries" in result.stdout


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    home = tmp_path_factory.mktemp("run")
    run_dir = home / "run"
    result = relocfw([*TINY_OVERRIDES, f"hydra.run.dir={run_dir}"], home, home / "cache")
    assert result.returncode == 0, result.stderr
    return home, run_dir


def test_localize_matches_the_evaluation_run(trained_run, tiny_scene):
    home, run_dir = trained_run
    scene = next((home / "cache" / "scenes").iterdir())
    out = home / "localize"
    result = relocfw(
        [
            "task=localize",
            f"localize.model={run_dir / 'model.relocfw'}",
            f"localize.images={scene / 'seq-03'}/*.color.png",
            "query.queries_at_once=3",  # over the model file's 1: the same answers
            f"hydra.run.dir={out}",
            "quiet=true",
        ],
        home,
        home / "cache",
    )
    assert result.returncode == 0, result.stderr
    assert result.stderr == ""
    poses = np.loadtxt(out / "poses.txt")  # TUM: t x y z qx qy qz qw
    rows = [line.split(",") for line in (run_dir / "results.csv").read_text().splitlines()]
    header, rows = rows[0], [r for r in rows[1:] if r[0] == "ga + kmeans (k=4)"]
    expected = np.array(
        [
            [
                float(r[header.index(c)])
                for c in ("est_x", "est_y", "est_z", "est_qx", "est_qy", "est_qz", "est_qw")
            ]
            for r in rows
        ]
    )
    assert np.allclose(poses[:, 1:], expected, atol=1e-5)
    # frame-000000.color.png ... are not times: the timestamp is the image's position.
    assert poses[:, 0].tolist() == [0, 1, 2, 3]


@pytest.mark.parametrize(
    "content, message",
    [
        (lambda good: good[: len(good) // 2], "model: cannot read"),
        (lambda good: b"not a model", "model: cannot read"),
    ],
)
def test_bad_model_files(trained_run, tmp_path, content, message):
    home, run_dir = trained_run
    bad = tmp_path / "bad.relocfw"
    bad.write_bytes(content((run_dir / "model.relocfw").read_bytes()))
    args = ["task=localize", f"localize.model={bad}", f"localize.images={tmp_path}"]
    result = relocfw_here(args, tmp_path)
    assert result.returncode == 2 and message in result.stderr and str(bad) in result.stderr


def test_model_file_of_another_format(trained_run, tmp_path):
    home, run_dir = trained_run
    payload = torch.load(run_dir / "model.relocfw", weights_only=True)
    payload["format"] = 99
    old = tmp_path / "old.relocfw"
    torch.save(payload, old)
    # In the spellings before issue 21: model= and images= are read as localize.*.
    result = relocfw_here(["task=localize", f"model={old}", f"images={tmp_path}"], tmp_path)
    assert result.returncode == 2 and "model format 99" in result.stderr
    notes = result.stderr.splitlines()[:2]
    assert notes == [
        f"note: model= is now localize.model= (read as localize.model={old})",
        f"note: images= is now localize.images= (read as localize.images={tmp_path})",
    ]


def test_localize_without_images(trained_run, tmp_path):
    home, run_dir = trained_run
    result = relocfw_here(
        [
            "task=localize",
            f"localize.model={run_dir / 'model.relocfw'}",
            f"localize.images={tmp_path}/*.png",
        ],
        tmp_path,
    )
    assert result.returncode == 2 and "no image files found" in result.stderr


def test_localize_refuses_depth_maps_as_images(trained_run, tmp_path):
    home, run_dir = trained_run
    sequence = next((home / "cache" / "scenes").iterdir()) / "seq-03"
    result = relocfw_here(
        [
            "task=localize",
            f"localize.model={run_dir / 'model.relocfw'}",
            f"localize.images={sequence}",
        ],
        tmp_path,
    )
    assert result.returncode == 2
    assert result.stderr == (
        f"error: localize.images={sequence}: 4 of the 8 files are depth maps "
        f"(frame-000000.depth.png, ...); name the colour images, e.g. "
        f"localize.images='{sequence}/*.color.png'\n"
    )


def test_killed_training_resumes(tmp_path):
    """SIGKILL mid-training, run again: it continues from the last checkpoint."""
    # Long enough that the kill lands mid-training (about 0.1 s a step on one of 2
    # cores), short enough that the resumed run is quick.
    args = [*TINY_OVERRIDES, "task=train", "train.iterations=150", "train.checkpoint_every=10"]
    env_cache = tmp_path / "cache"
    env = {**os.environ, "RELOCFW_CACHE": str(env_cache)}
    process = subprocess.Popen(
        [sys.executable, "-m", "relocfw", *args],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.time() + 120
    while time.time() < deadline and not list(env_cache.glob("checkpoints/*.pt")):
        time.sleep(0.05)
    time.sleep(0.3)
    process.send_signal(signal.SIGKILL)
    process.wait()
    checkpoints = list(env_cache.glob("checkpoints/*.pt"))
    assert checkpoints, "no checkpoint was written before the kill"
    # Whatever the kill interrupted, the checkpoint itself is whole and readable.
    assert not load_checkpoint(checkpoints[0])["complete"]
    # A kill that lands mid-write leaves a temporary; the cleaner spares temporaries
    # younger than its grace age (a writer may be about to lock one), so age any
    # left here past it: the resumed run must then remove them.
    past = time.time() - 2 * LOCKED_GRACE_SECONDS
    for temporary in env_cache.glob("checkpoints/.*"):
        os.utime(temporary, (past, past))
    again = relocfw(args, tmp_path, env_cache)
    assert not list(env_cache.glob("checkpoints/.*")), "a killed writer's temporary was left"
    assert again.returncode == 0, again.stderr
    assert "resumed from step" in again.stdout
    step = int(again.stdout.split("resumed from step ")[1].split(")")[0])
    assert 10 <= step < 150 and step % 10 == 0


def test_library_load_and_localize(trained_run):
    from relocfw import load_model
    from relocfw.core.imaging import read_rgb

    home, run_dir = trained_run
    relocalizer = load_model(run_dir / "model.relocfw")
    assert relocalizer.metadata["map_images"] == 16
    scene = next((home / "cache" / "scenes").iterdir())
    answer = relocalizer.localize(read_rgb(scene / "seq-03" / "frame-000000.color.png"))
    assert answer.pose.position.shape == (3,) and answer.evaluations >= 1


def fake_cuda(monkeypatch, devices):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: devices > 0)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: devices)


@pytest.mark.parametrize(
    "name, devices, message",
    [
        ("cuda:x", 2, "device=cuda:x is not a device name; use cpu, cuda, cuda:N or mps"),
        ("cuda:-1", 2, "device=cuda:-1 is not a device name"),
        ("gpu", 2, "device=gpu is not a device name"),
        ("cuda:2", 2, "device=cuda:2, but this machine has 2 CUDA device(s): use cuda:0 to cuda:1"),
        ("cuda:7", 1, "device=cuda:7, but this machine has 1 CUDA device(s): use cuda:0 to cuda:0"),
        ("cuda:0", 0, "device=cuda:0, but CUDA is not available here; use device=cpu"),
        ("cuda", 0, "device=cuda, but CUDA is not available here"),
    ],
    ids=["letter", "negative", "unknown type", "one past", "far past", "no cuda", "no cuda (any)"],
)
def test_a_device_that_is_not_there_is_refused_by_name(monkeypatch, name, devices, message):
    fake_cuda(monkeypatch, devices)
    with pytest.raises(ConfigError) as caught:
        pick_device(name)
    assert str(caught.value).startswith(message)


@pytest.mark.parametrize("name, devices", [("cuda:1", 2), ("cuda:0", 1), ("cuda", 1), ("cpu", 0)])
def test_a_device_that_is_there_is_accepted(monkeypatch, name, devices):
    fake_cuda(monkeypatch, devices)
    assert pick_device(name) == torch.device(name)


FAKE_TWO_GPUS = """import torch
torch.cuda.is_available = lambda: True
torch.cuda.device_count = lambda: 2
"""


@pytest.mark.parametrize(
    "device, fake, message",
    [
        ("cuda:x", False, "device=cuda:x is not a device name"),
        ("cuda:5", True, "device=cuda:5, but this machine has 2 CUDA device(s)"),
    ],
    ids=["malformed", "beyond the devices"],
)
def test_a_bad_device_index_ends_the_command_with_one_message(tmp_path, device, fake, message):
    args = [*TINY_OVERRIDES, f"device={device}"]
    if fake:  # this machine has no GPU: a sitecustomize makes torch report two
        (tmp_path / "fake").mkdir()
        (tmp_path / "fake" / "sitecustomize.py").write_text(FAKE_TWO_GPUS)
        result = relocfw(args, tmp_path, PYTHONPATH=str(tmp_path / "fake"))
    else:
        result = relocfw_here(args, tmp_path)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr
    assert result.stderr.count("error:") == 1 and "Traceback" not in result.stderr
    assert not (tmp_path / "cache").exists()  # refused before any scene was rendered
