"""The `relocfw` command end to end, on a tiny configuration: real processes for the
runs that work, this process (tests.cli_runs.relocfw_here) for refusals."""

import csv
import inspect
import json
import re
import shutil
import sys
from pathlib import Path

import pytest
import yaml

from relocfw.app import cli
from relocfw.app.config_schema import Task, name_of
from relocfw.app.spellings import rewrite
from relocfw.core.errors import ConfigError
from tests.cli_runs import relocfw, relocfw_here, users_methods
from tests.conftest import TINY_MODEL, TINY_OVERRIDES


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

    # A second method on the same model: the checkpoint is reused, not retrained. Its
    # query options are in the spellings before issue 21: read anew, one note each.
    old = ["query_batch_size=8", "baselines=[mean_pose,posenet]", "queries_at_once=2"]
    again = relocfw(
        [
            *TINY_OVERRIDES,
            "crop=sweep",
            "index=exhaustive",
            *old,
            f"hydra.run.dir={tmp_path / 'r2'}",
        ],
        tmp_path,
        cache,
    )
    assert again.returncode == 0, again.stderr
    assert again.stderr.splitlines() == [
        "note: query_batch_size= is now query.batch_size= (read as query.batch_size=8)",
        "note: baselines= is now relocalize.baselines= "
        "(read as relocalize.baselines=[mean_pose,posenet])",
        "note: queries_at_once= is now query.queries_at_once= (read as query.queries_at_once=2)",
    ]
    overrides = yaml.safe_load((tmp_path / "r2" / ".hydra" / "overrides.yaml").read_text())
    assert "query.batch_size=8" in overrides and "query_batch_size=8" not in overrides
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
    # Retrieval (refine=retrieval) has a confidence, minus the nearest map distance:
    # its uncertainty quality is measured as a sampled method's is.
    assert pngs == [
        "synthetic_Bayesian_PoseNet_uncertainty.png",
        "synthetic_Retrieval_uncertainty.png",
        "synthetic_error_per_image.png",
        "synthetic_orientation_error_histogram.png",
        "synthetic_position_error_histogram.png",
        "synthetic_trajectory_top_down.png",
        "synthetic_tsne_kmeans_map.png",
    ]
    summary = json.loads((run_dir / "comparison.json").read_text())
    assert "Bayesian PoseNet" in summary["scenes"]["synthetic"]["uncertainty"]
    assert "Retrieval" in summary["scenes"]["synthetic"]["uncertainty"]
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
        (["train.optimizer=rmsprop"], "train.optimizer=rmsprop: Invalid value 'rmsprop'"),
        (["train.log=wandb"], "expected one of [none, tensorboard]"),
        (["query.crop_samples=4", "train.crop_scale=1.0"], "the window fills the crop"),
        (["query.rerank=3"], "query.rerank=3 re-scores the best shared- or scout-scoring"),
        (
            ["query.scoring=scout"],
            "query.scoring=scout scores candidate crops with the static int8",
        ),
        (
            ["query.scoring=scout", "engine=torch"],
            "query.scoring=scout scores candidate crops with onnxruntime's int8 graph, but "
            "the network runs on torch here",
        ),
        (["query.queries_at_once=0"], "query.queries_at_once must be at least 1, got 0"),
        (["task=nosuch"], "task=nosuch: Invalid value 'nosuch', expected one of [relocalize,"),
        (["device=cuda:7"], "device"),
        (["task=compare", "compare.reference=Nobody"], "compare.reference"),
        # refine=retrieval: sampling the network's pose is refused, whatever the index.
        (
            ["refine=retrieval", "backbone.mc_samples=4"],
            "the refiner RetrievalRefiner never answers with the network's pose, but "
            "query.crop_samples=0 / backbone.mc_samples=4 sample that pose",
        ),
        (["refine=retrieval", "refine.k=0"], "refine=retrieval: refine.k must be at least 1"),
        (["index=faiss", "index.kind=lsh"], "index.kind must be one of flat, ivf, hnsw"),
        (["index=faiss", "index.kind=ivf"], "nlist=1024 is more IVF cells than map"),
        (["preset=paper"], "preset=paper fine-tunes ImageNet weights (train.lr=1e-05)"),
        (["backbone=bayesian_posenet", "preset=paper"], "or a pretrained backbone"),
        (["train.crop_scale=0.5"], "train.crop_scale must be in [1, 4]"),
    ],
)
def test_bad_options_end_in_one_clear_message(tmp_path, cache, args, message):
    tiny = TINY_MODEL if "dataset=sevenscenes" in args else TINY_OVERRIDES
    result = relocfw_here([*tiny, *args], tmp_path, cache)
    assert result.returncode == 2
    assert message in result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith("error: ") and "Traceback" not in result.stderr
    assert "model:" not in result.stdout  # refused before any training


def test_a_refusal_ends_a_real_process_with_one_line_and_status_2(tmp_path, cache):
    """The refusals above run in this process; one in a process of its own shows the
    exit status and the streams a user sees."""
    result = relocfw([*TINY_OVERRIDES, "k=500"], tmp_path, cache)
    assert result.returncode == 2
    assert result.stderr == (
        "error: k=500 is more clusters than training descriptors (16); choose k <= 16\n"
    )
    assert "model:" not in result.stdout


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["query.batch_size=abc"],
            "query.batch_size=abc: Value 'abc' of type 'str' could not be converted to Integer",
        ),
        (["query.scoring=fancy"], "query.scoring=fancy: Invalid value 'fancy', expected one of"),
        (
            ["task=localize", "engine=tf"],
            "engine=tf: Invalid value 'tf', expected one of [auto, torch, onnx, ncnn]",
        ),
        (  # the spelling before the engine: read as engine=tf (one note), then refused
            ["task=localize", "localize.backend=tf"],
            "engine=tf: Invalid value 'tf', expected one of [auto, torch, onnx, ncnn]",
        ),
        (
            ["onnx.int8=int4"],
            "onnx.int8=int4: Invalid value 'int4', expected one of "
            "[none, dynamic, static, static_8bit]",
        ),
    ],
    ids=["type", "choice", "engine", "old backend", "int8 choice"],
)
def test_a_wrong_type_or_choice_fails_before_any_work_in_one_line(tmp_path, args, message):
    result = relocfw_here([*TINY_OVERRIDES, *args], tmp_path)
    assert result.returncode == 2, result.stderr
    (line,) = [line for line in result.stderr.splitlines() if not line.startswith("note: ")]
    assert line.startswith(f"error: {message}"), result.stderr
    assert result.stdout == ""
    assert not (tmp_path / "cache").exists()  # nothing rendered, nothing trained
    assert not (tmp_path / "outputs").exists()  # not even a run directory


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["engine=torch", "onnx.int8=static"],
            "onnx.int8=static quantises the onnxruntime graphs, but the network runs on torch "
            "here (engine=torch): use engine=onnx on a CPU, or drop onnx.int8",
        ),
        (["onnx.threads=0"], "onnx.threads must be >= 1 (null: every core), got 0"),
        (
            # A compare row's own engine options, before the first row trains.
            ["task=compare", "methods=engine", "engine=torch", "compare.crop_seeds=null"],
            "compare row 'PoseNet, int8 static': onnx.int8=static quantises the onnxruntime "
            "graphs, but the network runs on torch here (engine=torch)",
        ),
    ],
    ids=["int8 on torch", "no threads", "a compare row's int8 on torch"],
)
def test_engine_options_that_cannot_apply_end_in_one_line_before_any_work(tmp_path, args, message):
    """Checked with the device, first thing in every task (even one that never runs
    the engine, such as training): a typo is refused, not ignored."""
    result = relocfw_here([*TINY_OVERRIDES, *args], tmp_path)
    assert result.returncode == 2, result.stderr
    (line,) = result.stderr.splitlines()
    assert line.startswith(f"error: {message}")
    assert result.stdout == ""
    assert not (tmp_path / "cache").exists()  # nothing rendered, nothing trained


def test_an_old_multirun_list_is_read_in_the_new_spelling(tmp_path):
    sweep = tmp_path / "multi"
    args = ["-m", "task=plugins", "scoring=plain,shared", f"hydra.sweep.dir={sweep}"]
    result = relocfw_here(args, tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stderr.splitlines() == [
        "note: scoring= is now query.scoring= (read as query.scoring=plain,shared)"
    ]
    for job, scoring in ((0, "plain"), (1, "shared")):
        overrides = yaml.safe_load((sweep / str(job) / ".hydra" / "overrides.yaml").read_text())
        assert f"query.scoring={scoring}" in overrides


@pytest.mark.parametrize(
    "old, task, new",
    [
        (["scoring=shared"], None, ["query.scoring=shared"]),
        (["+crop_samples=4", "~rerank"], None, ["+query.crop_samples=4", "~query.rerank"]),
        (["queries_at_once=1,5", "x=1"], None, ["query.queries_at_once=1,5", "x=1"]),
        (["task=export", "model=m.relocfw"], None, ["task=export", "export.model=m.relocfw"]),
        (["model=m.relocfw", "task=localize"], None, ["localize.model=m.relocfw", "task=localize"]),
        (["model=m"], "export", ["export.model=m"]),
        (["-m", "--config-name", "scoring"], None, ["-m", "--config-name", "scoring"]),
        (["pretrained_required=true"], None, ["train.pretrained_required=true"]),
        (["images=a/*.png", "backend=onnx"], None, ["localize.images=a/*.png", "engine=onnx"]),
        (["localize.backend=torch", "+backend=onnx"], None, ["engine=torch", "+engine=onnx"]),
        (["query.scoring=plain", "scoring_x=1"], None, ["query.scoring=plain", "scoring_x=1"]),
    ],
)
def test_old_spellings_are_rewritten_key_by_key(old, task, new):
    rewritten, found = rewrite(old, task)
    assert rewritten == new
    assert len(found) == len([o for o, n in zip(old, new, strict=True) if o != n])


def test_a_users_old_methods_file_still_works(tmp_path):
    """compare.methods rows in the old spellings are read in the new ones, one note per
    key (the file is composed but nothing runs: the reference is missing)."""
    rows = (
        "Shared: [crop=ga, scoring=shared, rerank=2]\nShared again: [crop=sweep, scoring=shared]\n"
    )
    methods = users_methods(tmp_path, "old", rows)
    args = [*TINY_OVERRIDES, "task=compare", *methods, "compare.reference=Nobody"]
    result = relocfw_here(args, tmp_path)
    assert result.returncode == 2
    assert result.stderr.splitlines() == [
        "note: scoring= is now query.scoring= "
        "(compare.methods.Shared: read as query.scoring=shared)",
        "note: rerank= is now query.rerank= (compare.methods.Shared: read as query.rerank=2)",
        "error: compare.reference='Nobody' is not in compare.methods",
    ]


@pytest.mark.parametrize(
    "old, k",
    [
        (["query.retrieval_k=3"], "3"),
        (["retrieval_k=2"], "2"),  # the spelling before issue 21
        (["+query.retrieval_k=1,5"], "1,5"),
    ],
)
def test_retrieval_k_ends_in_one_line_giving_the_new_spelling(tmp_path, old, k):
    """The retrieval baseline is refine=retrieval since issue 22: one override became
    two, so the old key is refused with the new spelling rather than rewritten."""
    result = relocfw_here([*TINY_OVERRIDES, *old], tmp_path)
    assert result.returncode == 2
    (line,) = result.stderr.splitlines()
    key = old[0].lstrip("+").split("=")[0]
    assert line == (
        f"error: {old[0]}: {key} is no longer an option; the image-retrieval baseline is "
        f"a refiner now: write refine=retrieval refine.k={k}"
    )
    assert result.stdout == ""
    assert not (tmp_path / "outputs").exists()  # refused before Hydra ran


@pytest.mark.parametrize(
    "old", ["query.retrieval_k=0", "query.retrieval_k=null", "~query.retrieval_k", "~retrieval_k=1"]
)
def test_retrieval_k_0_is_refused_with_what_it_meant(old):
    # 0, null (the old default) and deleting the key all meant: no retrieval.
    with pytest.raises(ConfigError, match="drop it \\(refine=none, the default"):
        rewrite([old])


def test_an_old_methods_row_with_retrieval_k_names_the_row(tmp_path):
    rows = "Retrieval: [crop=centre, index=exhaustive, retrieval_k=1]\n"
    args = [*TINY_OVERRIDES, "task=compare", *users_methods(tmp_path, "old", rows)]
    result = relocfw_here(args, tmp_path)
    assert result.returncode == 2
    assert result.stderr.splitlines() == [
        "error: compare.methods.Retrieval: retrieval_k=1: retrieval_k is no longer an option; "
        "the image-retrieval baseline is a refiner now: write refine=retrieval refine.k=1"
    ]


def test_the_dispatch_table_runs_every_task():
    assert sorted(cli.TASKS) == sorted(task.value for task in Task)
    for name, run in cli.TASKS.items():
        assert run.__name__ == "run" and run.__module__ == f"relocfw.app.tasks.{name}"
        assert list(inspect.signature(run).parameters) == ["cfg", "device", "world"], name


def test_the_main_job_has_no_option_outside_its_groups():
    """The top level keeps task, seed, device, engine, cache_dir, quiet and k; every
    other option sits in a group (query., localize., onnx., ...)."""
    from hydra import compose, initialize_config_module

    with initialize_config_module(config_module="relocfw.conf", version_base="1.3"):
        cfg = compose("config")
    plain = {key for key, value in cfg.items() if not hasattr(value, "keys")}
    assert plain == {"task", "seed", "device", "engine", "cache_dir", "quiet", "k"}
    assert set(cfg) - plain == {
        *("backbone", "index", "crop", "refine", "dataset", "query", "localize", "export"),
        *("relocalize", "compare", "diagnose", "train", "onnx", "serve", "calibrate"),
    }
    assert (name_of(cfg.engine), name_of(cfg.onnx.int8)) == ("auto", "none")
    assert all(value is None for value in cfg.query.values())  # each task's default


def test_the_centre_crop_row_says_when_it_samples_dropout(tmp_path, cache):
    run_dir = tmp_path / "run"
    args = [*TINY_OVERRIDES, "backbone.mc_samples=2", f"hydra.run.dir={run_dir}"]
    result = relocfw(args, tmp_path, cache)
    assert result.returncode == 0, result.stderr
    methods = [s["method"] for s in json.loads((run_dir / "summary.json").read_text())]
    assert methods[1] == "posenet x2 MC dropout (centre crop)"
    assert "posenet (centre crop)" not in result.stdout


def test_compare_rows_say_when_the_command_line_samples_dropout(tmp_path, cache, tiny_scene):
    # On a 7-Scenes layout whose scene is "room": the reports name the scene, not the
    # loader (sevenscenes).
    shutil.copytree(tiny_scene, tmp_path / "data" / "room")
    scene = ["dataset=sevenscenes", f"dataset.root={tmp_path / 'data'}", "dataset.scene=room"]
    run_dir = tmp_path / "compare"
    methods = '+compare.methods={PoseNet:["crop=centre"],Bayes:["backbone.mc_samples=3"]}'
    args = [*TINY_MODEL, *scene, "task=compare", "~compare.methods", methods]
    args += ["backbone.mc_samples=2", "crop=centre", "compare.crop_seeds=null"]
    result = relocfw([*args, f"hydra.run.dir={run_dir}"], tmp_path, cache)
    assert result.returncode == 0, result.stderr
    header = (run_dir / "comparison.csv").read_text().splitlines()[0]
    # PoseNet did not ask for sampling but got it from the command line: it says so.
    assert "PoseNet (x2 MC dropout) (m, deg)" in header
    assert "Bayes (m, deg)" in header  # asked for its own samples: its name stands
    assert "| room |" in (run_dir / "comparison.md").read_text()
    assert list(json.loads((run_dir / "comparison.json").read_text())["scenes"]) == ["room"]
    assert (run_dir / "table_room.txt").is_file() and (
        run_dir / "room_error_per_image.png"
    ).is_file()
    assert "sevenscenes" not in result.stdout and not list(run_dir.glob("sevenscenes*"))


def test_corrupt_image_names_the_file(tmp_path, cache, tiny_scene):
    root = tmp_path / "data"
    shutil.copytree(tiny_scene, root / "room")
    bad = root / "room" / "seq-01" / "frame-000004.color.png"
    bad.write_bytes(b"\x89PNG truncated")
    result = relocfw_here(
        [*TINY_MODEL, "dataset=sevenscenes", f"dataset.root={root}", "dataset.scene=room"],
        tmp_path,
        cache,
    )
    assert result.returncode == 2
    assert f"cannot decode image (corrupt or not an image): {bad}" in result.stderr


def test_help_lists_the_options_with_their_package(tmp_path):
    result = relocfw_here(["--help"], tmp_path)
    assert result.returncode == 0
    assert "crop (CropSearch):" in result.stdout and "index (SimilarityIndex):" in result.stdout
    for option in ("centre", "ga", "sweep", "exhaustive", "kmeans", "posenet", "tum"):
        assert re.search(rf"\n  {option}\s+\[relocfw\] ", result.stdout), option


def test_console_script_is_installed():
    script = Path(sys.executable).with_name("relocfw")
    assert script.is_file(), "pip install -e . should install the relocfw command"


SHIPPED_METHODS = Path(__file__).parents[2] / "conf" / "methods"


@pytest.mark.parametrize("methods", sorted(p.stem for p in SHIPPED_METHODS.glob("*.yaml")))
def test_every_shipped_methods_row_composes(methods, monkeypatch):
    """A typo in a shipped methods=NAME row (an unknown key, a value the schema
    refuses, engine options that cannot go together) would otherwise surface only
    after the rows before it trained. The CPU is taken to have VNNI: whether it does
    is the machine's business, tested in tests/model/test_onnx_engine.py."""
    import torch
    from hydra import compose, initialize_config_module

    from relocfw.app.engines import wanted_engine
    from relocfw.app.tasks.compare import method_rows
    from relocfw.model import cpu_flags

    monkeypatch.setattr(cpu_flags, "int8_saturation_reason", lambda: None)
    with initialize_config_module(config_module="relocfw.conf", version_base="1.3"):
        cfg = compose("config", overrides=[f"methods={methods}"])
        rows = method_rows(cfg)
        assert rows, methods
        for overrides in rows.values():
            row = compose("config", overrides=[f"methods={methods}", *overrides])
            assert wanted_engine(row, torch.device("cpu")) in ("torch", "onnx", "ncnn")


def test_compare_rows_with_their_own_dataset_options_are_refused(tmp_path):
    # Each scene's frames are loaded once, with the first row's dataset options: a
    # row's own dataset.* would silently answer with the first row's frames.
    rows = "PoseNet: [crop=centre]\nFewer queries: [crop=centre, dataset.test_frames=3]\n"
    args = [*TINY_OVERRIDES, "task=compare", *users_methods(tmp_path, "poses", rows)]
    result = relocfw_here(args, tmp_path)
    assert result.returncode == 2
    assert result.stderr.splitlines()[-1].startswith(
        "error: compare rows 'PoseNet', 'Fewer queries' set different dataset.* options"
    )
