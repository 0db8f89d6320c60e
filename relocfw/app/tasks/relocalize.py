"""task=relocalize (the main job): train or reuse the model, fit the map, relocalize
the test split beside the baselines, and save the model file."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from relocfw.app.config_schema import Baseline, name_of
from relocfw.app.engines import keep_graphs_beside, on_engine
from relocfw.app.methods import centre_label, dataset_settings, scene_name
from relocfw.app.results import Split, fit_method, run_method, write_results
from relocfw.app.split_record import split_record
from relocfw.app.splits import load_split, write_skipped
from relocfw.app.tasks.train import trained
from relocfw.app.validation_block import held_out_count
from relocfw.core.pipeline import Relocalizer
from relocfw.core.query_options import QueryOptions
from relocfw.core.version import VERSION
from relocfw.data.frames import mean_pose
from relocfw.model.distributed import World
from relocfw.model.model_file import save_model, stores_refiner
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.report.calibration import Calibration
from relocfw.report.evaluation import MethodResult, constant_answer, evaluate
from relocfw.report.units import METRES, PositionUnit, unit_of

BASELINES = tuple(b.value for b in Baseline)


def relocalize(
    relocalizer: Relocalizer,
    method: str,
    train: Split,
    test: Split,
    run_dir: Path,
    baselines: Sequence[str] = BASELINES,
    centre_label: str = "posenet (centre crop)",
    quiet: bool = False,
    unit: PositionUnit = METRES,
    calibration: Calibration | None = None,
    split: dict | None = None,
) -> list[MethodResult]:
    """The main job after training: the method and its baselines, results written
    with the positions' `unit` (relocfw.report.units.unit_of the dataset) and the run's
    `split` record (relocfw.app.split_record). With a `calibration` block, the method's
    answers carry calibrated error bounds."""
    results = []
    if "mean_pose" in baselines:
        results.append(constant_answer("mean training pose", mean_pose(train[0]), test[0]))
    method_result, _ = run_method(method, relocalizer, train, test, quiet, calibration)
    options = relocalizer.options
    if "posenet" in baselines and not (
        isinstance(relocalizer.search, CentreCrop) and relocalizer.refiner is None
    ):
        # PoseNet: the centre crop of the same network and map, sampled as the method's
        # network is (backbone.mc_samples), with its seed; no random crops, no refiner.
        # Unless the method is that already.
        plain = QueryOptions(
            batch_size=options.batch_size,
            sample_seed=options.sample_seed,
            queries_at_once=options.queries_at_once,
        )
        centre = Relocalizer(
            relocalizer.backbone, relocalizer.index, CentreCrop(), plain, relocalizer.device
        )
        # The map is already fitted; only the queries run again.
        results.append(evaluate(centre_label, centre, *test, quiet=quiet))
    results.append(method_result)
    print(write_results(results, run_dir, unit=unit, split=split))
    print(f"\nresults: {Path(run_dir) / 'results.csv'}, {Path(run_dir) / 'summary.json'}")
    if unit.note:
        print(f"note: {unit.note}")
    return results


def test_split(dataset: object, quiet: bool) -> Split | None:
    """The test split; None where the dataset holds no test frames by design
    (dataset=rosbag without dataset.test_time: the recording is all map)."""
    if not getattr(dataset, "has_test_split", True):
        return None
    return load_split(dataset, "test", quiet)


def nothing_scored(dataset: object, map_images: int) -> str:
    """The one line a run without test frames prints in place of the results table."""
    describe = getattr(dataset, "split_source", None)
    why = describe("test") if describe is not None else "the dataset has none"
    return f"nothing was scored: no test frames ({why}); the map holds {map_images} images"


def run(cfg: DictConfig, device: torch.device, world: World | None) -> None:
    done = trained(cfg, device, world, map_size=True)
    choices = HydraConfig.get().runtime.choices
    quiet = bool(cfg.quiet)
    test = test_split(done.dataset, quiet)
    write_skipped(done.dataset, done.run_dir)
    method = done.method
    relocalizer = on_engine(cfg, method.relocalizer(device), done.checkpoint, device, done.train[1])
    if test is None:
        fit_method(method.label, relocalizer, done.train, quiet, done.calibration)
        print(nothing_scored(done.dataset, len(done.train[0])))
    else:
        relocalize(
            relocalizer,
            method.label,
            done.train,
            test,
            done.run_dir,
            baselines=[name_of(b) for b in cfg.relocalize.baselines],
            centre_label=centre_label(cfg, choices),
            quiet=quiet,
            unit=unit_of(done.dataset),
            calibration=done.calibration,
            split=split_record(done.dataset, done.train[0], test[0], done.calibration),
        )
    metadata = {
        "method": method.label,
        "dataset": choices["dataset"],
        "scene": scene_name(cfg, choices),
        "dataset_settings": dataset_settings(cfg),
        "map_images": len(done.train[0]),
        "validation_images": held_out_count(done.calibration),
        "checkpoint": str(done.checkpoint),
        "relocfw_version": VERSION,
    }
    model = save_model(done.run_dir / "model.relocfw", relocalizer, method.part_options, metadata)
    keep_graphs_beside(relocalizer, done.checkpoint, model)
    print(
        f"model file: {model}  (relocfw task=localize localize.model={model} localize.images=...)"
    )
    if method.refiner is not None and not stores_refiner(relocalizer):
        print(
            f"note: {model.name} holds the network, map and crop search, not the "
            f"refine={choices['refine']} stage ({type(method.refiner).__name__} cannot be "
            "stored in a model file): task=localize answers with the network's pose"
        )
