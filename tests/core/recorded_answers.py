"""Recorded crops and poses of the pipeline, to hold a rewrite of it to the same answers.

`recorded_answers.json` beside this file was written by the pipeline before the crop
searches became ask/tell (issue 21, commit 951e255); `test_recorded_answers.py` checks
today's pipeline against it. Re-record only on a deliberate change of answers:

    .venv/bin/python tests/core/recorded_answers.py --write

Every case is deterministic: a seeded, untrained GoogLeNet at 1/8 width on the tiny
rendered scene (its windows' descriptors differ, so the searches have work to do).
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import torch

RECORD = Path(__file__).with_name("recorded_answers.json")
CASES = ("centre", "sweep", "ga", "ga_shared", "ga_shared_rerank", "mc_sampling", "retrieval")


def scene_images(cache: Path) -> tuple[list, list, list]:
    from relocfw.data.frames import read_images
    from relocfw.data.sevenscenes import load_sevenscenes
    from relocfw.data.synthetic import SyntheticSceneSpec, ensure_synthetic_scene

    spec = SyntheticSceneSpec(
        width=80, height=36, train_laps=2, train_frames_per_lap=8, test_frames=6
    )
    root = ensure_synthetic_scene(spec, cache, quiet=True)
    train_frames = load_sevenscenes(root, None, "train")
    train = read_images(train_frames, quiet=True)
    test = read_images(load_sevenscenes(root, None, "test"), quiet=True)
    return train, [frame.pose for frame in train_frames], test


def relocalizer_for(case: str):
    """The pipeline of one case. Only this function follows the pipeline's API."""
    from relocfw import QueryOptions, Relocalizer
    from relocfw.plugins.centre_crop import CentreCrop
    from relocfw.plugins.exhaustive_index import ExhaustiveIndex
    from relocfw.plugins.ga_crop import GeneticCropSearch
    from relocfw.plugins.kmeans_index import KMeansIndex
    from relocfw.plugins.posenet import PoseNet
    from relocfw.plugins.retrieval_refiner import RetrievalRefiner
    from relocfw.plugins.sweep_crop import SweepCrop

    torch.manual_seed(0)
    sampled = case == "mc_sampling"
    backbone = PoseNet(
        input_size=32,
        width=0.125,
        feature_dim=32,
        **({"mc_samples": 6, "dropout_variant": "kendall"} if sampled else {}),
    )
    if sampled:
        backbone.set_crop_scale(1.5)
    search = {
        "centre": CentreCrop(),
        "sweep": SweepCrop(),
        "retrieval": CentreCrop(),
    }.get(case) or GeneticCropSearch(seed=3)
    index = ExhaustiveIndex() if case in ("mc_sampling", "retrieval") else KMeansIndex(k=4)
    options = {
        "ga_shared": {"scoring": "shared"},
        "ga_shared_rerank": {"scoring": "shared", "rerank": 3},
        "mc_sampling": {"crop_samples": 5, "sample_seed": 2},
    }.get(case, {})
    # Recorded as the query option retrieval_k=2; the refiner since issue 22 (same poses).
    refiner = RetrievalRefiner(k=2) if case == "retrieval" else None
    return Relocalizer(
        backbone, index, search, QueryOptions(batch_size=8, **options), refiner=refiner
    )


def answers(case: str, cache: Path) -> list[dict]:
    train, poses, test = scene_images(cache)
    relocalizer = relocalizer_for(case)
    relocalizer.fit(train, poses)
    return [
        {
            "crop": [answer.crop.x, answer.crop.y, answer.crop.size],
            "distance": float(answer.distance),
            "position": answer.pose.position.tolist(),
            "quaternion": answer.pose.quaternion.tolist(),
            "evaluations": int(answer.evaluations),
            "position_spread": float(answer.position_spread),
        }
        for answer in (relocalizer.localize(image) for image in test)
    ]


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        sys.exit(__doc__)
    with tempfile.TemporaryDirectory() as cache:
        record = {case: answers(case, Path(cache)) for case in CASES}
    RECORD.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {RECORD}")
