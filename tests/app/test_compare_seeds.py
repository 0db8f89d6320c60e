"""task=compare's reruns of a randomised crop search with each crop seed."""

from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from relocfw.app.tasks.compare import rerun_crop_seeds
from relocfw.core.values import Crop, Localization, Pose
from relocfw.data.frames import Frame
from relocfw.report.evaluation import MethodResult


class SeedEchoRelocalizer:
    """Answers each query with its crop search's seed as the x position."""

    def __init__(self, search):
        self.search = search

    def localize(self, image):
        pose = Pose([float(self.search.seed), 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
        return Localization(pose, Crop(0, 0, 1), 0.0, 1, 0.0)


def test_each_crop_seed_is_used_once_and_the_configured_search_is_put_back():
    cfg = OmegaConf.create(
        {
            "seed": 1,
            "crop": {"_target_": "relocfw.plugins.ga_crop.GeneticCropSearch", "seed": "${seed}"},
        }
    )
    configured = object()
    relocalizer = SeedEchoRelocalizer(configured)
    truth = Pose(np.zeros(3), [1.0, 0.0, 0.0, 0.0])
    frames = [Frame(f"q{i}", Path(f"q{i}.png"), truth) for i in range(3)]
    images = [np.zeros((4, 6, 3), np.uint8)] * 3
    main_run = MethodResult("GA", tuple(frames), ())
    runs = rerun_crop_seeds(
        cfg, {"crop": "ga"}, relocalizer, main_run, (frames, images), [0, 1, 2], True
    )
    assert sorted(runs) == [0, 1, 2]
    assert runs[1] is main_run  # crop.seed resolves to seed=1: the main table's run
    for seed in (0, 2):
        assert [a.pose.position[0] for a in runs[seed].answers] == [seed] * 3
        assert runs[seed].method == f"GA, crop.seed={seed}"
    assert relocalizer.search is configured
    assert OmegaConf.to_yaml(cfg).count("${seed}") == 1  # the composed config is untouched
