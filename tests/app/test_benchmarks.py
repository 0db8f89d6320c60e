"""The benchmark scripts still run and write their JSON (tiny sizes; numbers not checked)."""

import importlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

from relocfw.model.cpu_flags import int8_saturation_reason
from relocfw.model.ncnn_engine import ncnn_installed

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def run_script(name: str, out: Path, *args: str) -> dict:
    command = [sys.executable, str(BENCHMARKS / name), "--out", str(out), *args]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(out.read_text())


def test_query_cost(tmp_path):
    report = run_script(
        "query_cost.py",
        tmp_path / "q.json",
        "--queries",
        "1",
        "--map-images",
        "4",
        "--input-size",
        "32",
    )
    rows = {(r["search"], r["scoring"]): r for r in report["rows"]}
    assert rows["centre", "plain"]["network_passes"] == 1
    assert rows["ga", "shared"]["network_passes"] < rows["ga", "plain"]["network_passes"]


def test_training_throughput(tmp_path):
    report = run_script(
        "training_throughput.py",
        tmp_path / "t.json",
        "--steps",
        "1",
        "--rounds",
        "1",
        "--batch-size",
        "2",
        "--images",
        "4",
        "--input-size",
        "32",
    )
    assert report["bare_images_per_second"] > 0 and report["train_images_per_second"] > 0


def test_index_scale(tmp_path):
    pytest.importorskip("faiss")
    report = run_script(
        "index_scale.py",
        tmp_path / "i.json",
        "--sizes",
        "400",
        "--dim",
        "16",
        "--queries",
        "10",
        "--nprobe",
        "4",
        "--ef-search",
        "16",
        "--pca-dim",
        "8",
    )
    names = {r["index"] for r in report["rows"]}
    assert "faiss flat (exact)" in names and "exhaustive (numpy float64)" in names
    exact = [r for r in report["rows"] if r["index"] == "exhaustive (numpy float64)"]
    assert exact[0]["recall_at_1"] == 1.0  # numpy and faiss agree on the nearest


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    """A model file from the CLI on the tiny scene, and the cache its scene is in."""
    import os

    from tests.conftest import TINY_OVERRIDES

    root = tmp_path_factory.mktemp("benchmark-model")
    cache = root / "cache"
    command = [sys.executable, "-m", "relocfw", *TINY_OVERRIDES, f"hydra.run.dir={root / 'run'}"]
    env = {**os.environ, "RELOCFW_CACHE": str(cache)}
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    return root / "run" / "model.relocfw", cache


def test_faithful_scoring(tmp_path, tiny_model):
    model, cache = tiny_model
    report = run_script(
        "faithful_scoring.py",
        tmp_path / "f.json",
        "--model",
        str(model),
        "--cache",
        str(cache),
        "--rerank",
        "1",
        "100",
    )
    rows = {r["setting"]: r for r in report["rows"]}
    # Re-scoring every window plainly is the plain sweep: full agreement, same minimum.
    assert rows["sweep shared m=100"]["agreement"] == 1.0
    assert rows["sweep shared m=100"]["median_distance_ratio"] == pytest.approx(1.0)
    assert rows["centre"]["times_centre"] == 1.0 and "verdict" in report


def test_batched_throughput(tmp_path, tiny_model):
    model, cache = tiny_model
    report = run_script(
        "batched_throughput.py",
        tmp_path / "b.json",
        "--model",
        str(model),
        "--cache",
        str(cache),
        "--group",
        "3",
        "--repeats",
        "1",
    )
    for row in report["rows"]:
        assert row["same_crop"] == 1.0 and row["max_pose_difference_m"] < 1e-5


def test_cost_scaling(tmp_path, tiny_model, monkeypatch):
    model, cache = tiny_model
    report = run_script(
        "cost_scaling.py",
        tmp_path / "c.json",
        "--queries",
        "1",
        "--map-images",
        "4",
        "--input-size",
        "32",
        "--only",
        "ga",
        "map",
        "--model",
        str(model),
        "--cache",
        str(cache),
        "--map-sizes",
        "20",
        "40",
    )
    assert [r["population"] for r in report["ga_budgets"]] == [10, 20, 10, 20, 40]
    assert {r["map_descriptors"] for r in report["map_sizes"]} == {20, 40}


def test_engine_ceiling(tmp_path):
    pytest.importorskip("onnxruntime", reason='onnxruntime not installed ("relocfw[onnx]")')
    report = run_script(
        "engine_ceiling.py",
        tmp_path / "c.json",
        "--repeats",
        "2",
        "--batch",
        "2",
        "--matmul-size",
        "128",
        "--ga-queries",
        "1",
        "--input-size",
        "48",
        "--width",
        "0.25",
    )
    engines = {r["engine"] for r in report["rows"]}
    assert {"torch float32", "onnxruntime float32", "onnxruntime int8 static"} <= engines
    if ncnn_installed():
        assert "ncnn float32 (Winograd)" in engines
        assert report["ncnn_largest_relative_descriptor_difference"] < 1e-4
    assert report["multiply_adds_per_batch"] > 0
    assert sum(report["share_of_multiply_adds_by_kernel"].values()) == pytest.approx(1)
    assert 0 < report["plain_ga_on_onnxruntime"]["network_share"] <= 1
    assert report["plain_ga_on_onnxruntime"]["runs_per_query"] >= 1
    assert report["plain_ga_on_onnxruntime"]["crops_per_query"] >= 1
    assert report["peak_giga_multiply_adds_per_s"]["float32"] > 0
    assert all(r["ms_per_batch"] > 0 for r in report["rows"])


def test_engine_cost(tmp_path):
    pytest.importorskip("onnxruntime", reason="relocfw[onnx] not installed")
    # The full and maps graphs, torch's samples, and a search for the int8 scout. The
    # sweep, not the GA: float32 engines differ from torch in the 7th digit, which on
    # another CPU flipped one near-tie in a GA's ranking and so its whole later search
    # (CI: the same crop in 1 of 2 queries). A sweep scores fixed windows, so only a
    # tie between its two best could flip it; the GA still runs in the threads study.
    methods = ["centre", "mc kendall x40", "sweep plain"]
    report = run_script(
        "engine_cost.py",
        tmp_path / "e.json",
        "--queries",
        "2",
        "--warmup",
        "0",
        "--map-images",
        "4",
        "--geometry",
        "paper",
        "--input-size",
        "48",
        "--width",
        "0.25",
        "--view-size",
        "160",
        "120",
        "--threads-study",
        "--methods",
        *methods,
    )
    spinning = sorted({r["engine"] for r in report["threads"]["spinning"]})
    assert len(spinning) == 2 and spinning[1] == spinning[0] + " spin"
    assert {r["method"] for r in report["threads"]["threads"]} == {"centre", "ga plain"}
    rows = report["geometries"]["paper"]
    engines = ["torch", "onnx", "onnx-int8"]
    if int8_saturation_reason() is None:  # 8-bit weights run only where the CPU has VNNI
        engines.append("onnx-int8-8bit")
    ncnn = ncnn_installed()
    if ncnn:
        engines.append("ncnn")
    expected = {(m, e) for m in methods for e in engines}
    scouts = ("onnx-int8-scout", "onnx-int8-scout-best3")
    expected |= {(m, e) for m in methods for e in scouts if m in ("ga plain", "sweep plain")}
    assert {(r["method"], r["engine"]) for r in rows} == expected
    assert all(r["ms_per_query"] > 0 for r in rows)
    threads = {r["engine"] for r in report["threads"]["threads"]}
    assert ("ncnn 1t" in threads) == ncnn
    for row in rows:  # float32 engines answer as torch does; int8 only runs
        if row["engine"] in ("onnx", "ncnn"):
            assert row["same_crop_as_torch"] == 1.0
            assert row["max_position_difference_m"] < 1e-4


REDKITCHEN = Path(__file__).resolve().parents[3] / "shared" / "data" / "7scenes-redkitchen"


@pytest.mark.skipif(not REDKITCHEN.is_dir(), reason=f"{REDKITCHEN} is absent")
def test_structure_build_cost(tmp_path):
    pytest.importorskip("poselib", reason="relocfw[structure] not installed")
    # 6 real frames: the 12-image map cycles through them twice.
    report = run_script(
        "structure_build_cost.py",
        tmp_path / "s.json",
        "--data",
        str(REDKITCHEN),
        "--map-sizes",
        "6",
        "12",
        "--real-frames",
        "6",
        "--queries",
        "2",
        "--threads",
        "1",
        "--map-dir",
        str(tmp_path / "maps"),
    )
    assert report["complete"] and {"opencv", "poselib"} <= report["versions"].keys()
    small, cycled = report["builds"]
    assert (small["images"], small["distinct_frames"], small["views_per_frame"]) == (6, 6, 1)
    assert (cycled["images"], cycled["distinct_frames"], cycled["views_per_frame"]) == (12, 6, 2)
    for row in report["builds"]:
        assert not row["extrapolated"] and row["measured_images"] == row["images"]
        assert all(seconds > 0 for seconds in row["seconds"].values()), row["seconds"]
        assert row["file_bytes"] > 0 and row["points"] > 0
    # Repeated views are the same frames again: exactly twice the points.
    assert cycled["points"] == 2 * small["points"]
    query = report["query"]
    assert query["queries"] == 2 and query["map_images"] == 6
    assert all(query["median_ms"][part] > 0 for part in ("features", "matching", "total"))


def test_mc_sampled_part(tmp_path):
    pytest.importorskip("onnxruntime", reason="relocfw[onnx] not installed")
    report = run_script(
        "mc_sampled_part.py",
        tmp_path / "m.json",
        "--samples",
        "4",
        "--repeats",
        "1",
        "--input-size",
        "64",
    )
    assert [r["way"] for r in report["rows"]] == [
        "torch",
        "onnxruntime graph, masks as inputs",
        "onnxruntime graph, masks drawn by torch",
        "drawing torch's masks only",
    ]
    assert all(r["ms"] > 0 for r in report["rows"])


def test_learned_cost(tmp_path):
    tiny = ["--size", "32", "--batch-size", "2", "--rounds", "1", "--steps", "1"]
    sequence = ["--map-images", "20", "--window", "3", "--sequence-steps", "5"]
    report = run_script("learned_cost.py", tmp_path / "l.json", *tiny, "--queries", "1", *sequence)
    rows = {row["method"]: row for row in report["rows"]}
    # The hourglass is the same encoder plus a decoder: more weights, never fewer.
    assert (
        rows["Hourglass"]["parameters_millions"]
        > rows["PoseNet (EfficientNet-Lite0)"]["parameters_millions"]
    )
    assert report["sequence_model"]["fit_s"] > 0 and report["sequence_model"]["query_ms"] > 0


def test_selection_rules_answers_one_synthetic_scene_for_every_seed(tmp_path, monkeypatch):
    # The synthetic scene is rendered from the run's seed; without pinning it, training
    # seeds 1 and 2 would answer other scenes than seed 0 and the validation laps.
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    selection_rules = importlib.import_module("selection_rules")
    assert selection_rules.dataset_overrides("synthetic", "test", tmp_path) == ["dataset.seed=0"]


@pytest.mark.skipif(not REDKITCHEN.is_dir(), reason=f"{REDKITCHEN} is absent")
def test_matching_precision(tmp_path):
    report = run_script(
        "matching_precision.py",
        tmp_path / "p.json",
        "--data",
        str(REDKITCHEN),
        "--queries",
        "2",
        "--keyframes",
        "3",
        "--repeats",
        "1",
        "--threads",
        "1",
    )
    assert report["queries"] == 2 and report["float32_matches"] > 50
    assert 0.9 < report["bfloat16_keeps_share"] <= 1.0
    assert all(ms > 0 for ms in report["median_ms"].values())


@pytest.mark.skipif(not REDKITCHEN.is_dir(), reason=f"{REDKITCHEN} is absent")
def test_structure_scale(tmp_path):
    pytest.importorskip("poselib", reason="relocfw[structure] not installed")
    pytest.importorskip("faiss", reason="relocfw[faiss] not installed")
    # 6 real frames built twice (one worker, a pool of two); maps of 6 and 12 images.
    report = run_script(
        "structure_scale.py",
        tmp_path / "s.json",
        "--data",
        str(REDKITCHEN),
        "--sizes",
        "6",
        "12",
        "--build-frames",
        "6",
        "--workers",
        "1",
        "2",
        "--opencv-threads",
        "0",
        "--queries",
        "2",
        "--codes",
        "128",
        "--scale-code",
        "8",
        "--retrieval-dim",
        "256",
        "--faiss-kinds",
        "flat",
        "--map-dir",
        str(tmp_path / "maps"),
    )
    assert report["complete"]
    serial, pool = report["builds"]
    assert (serial["workers"], pool["workers"]) == (1, 2) and pool["same_map_as_first"]
    assert [c["code_bytes"] for c in report["codes"]] == [128, 8]
    small, large = report["rows"]
    assert (small["map_images"], large["map_images"]) == (6, 12)
    assert large["copies"] == 2 and large["extrapolated"] == ["build", "in_memory_layout"]
    # Exact faiss finds today's exhaustive keyframes; copies hold the same rows.
    assert large["retrieval"]["faiss flat"]["recall_of_exhaustive_keyframes"] == 1.0
    assert large["disk_bytes_per_image"] < small["disk_bytes_per_image"]  # centres shared
    assert large["query"]["failures"] == 0
    assert set(report["done_when"]) >= {"query_growth_met", "bytes_met"}


@pytest.mark.skipif(not REDKITCHEN.is_dir(), reason=f"{REDKITCHEN} is absent")
def test_block_consistency(tmp_path):
    pytest.importorskip("poselib", reason="relocfw[structure] not installed")
    # Every 20th frame mapped (35 images), every 50th a query (14), three keyframes.
    report = run_script(
        "block_consistency.py",
        tmp_path / "b.json",
        "--step",
        "20",
        "--query-step",
        "50",
        "--keyframes",
        "3",
        "--exclude",
        "5",
        "--near",
        "10",
    )
    assert report["map_images"] == 35
    pairs = report["pairs"]
    # With every block within 10 m, each query is solved against all seven blocks.
    assert len(pairs) == 49 and all(p["queries"] == 2 for p in pairs)
    own = [p for p in pairs if p["apart"] == 0]
    assert len(own) == 7 and set(report["by_blocks_apart"]) == {str(a) for a in range(7)}
    solved = [p for p in pairs if p["median_position_m"] is not None]
    assert solved and all(0 <= p["median_shift_m"] <= 10 for p in solved)


def test_int8_deviation(tmp_path):
    pytest.importorskip("onnxruntime", reason="relocfw[onnx] not installed")
    report = run_script("int8_deviation.py", tmp_path / "i.json", "--opens", "3")
    outputs = report["outputs"]
    assert set(outputs) == {"positions", "quaternions", "features"}
    for row in outputs.values():  # a genuine graph within its bound, another seed's beyond
        assert row["genuine_largest"] <= row["bound"]
    assert outputs["quaternions"]["other_weights_smallest"] > outputs["quaternions"]["bound"]
