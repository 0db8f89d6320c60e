"""What a run mapped, validated and tested on, and which poses it scored against: the
`split` record every results file carries, built here and only here.

A number means little without its split and its reference: 7-Scenes' far split tests
on sequences 5-7, and settings chosen on blocks of those sequences are not held out;
its two pseudo ground truths (KinectFusion's `.pose.txt` and an SfM file, dataset.pgt)
disagree by centimetres. The record says both, as data:

    train_sequences   the map's (and network's) sequence numbers, or None where the
                      dataset's frames are not numbered sequences (`seq-NN/frame-...`)
    train_source      what listed them (the option or split file, as the dataset says)
    validation        None, or what the run held out or chose settings on:
                        query_sequences (and query_source): the run's queries, when
                          compare.validation_for marks it as choosing settings for
                          another split's test;
                        calibration_block: the frames carved from the end of the
                          training split for error bounds (calibrate.share)
    test_sequences    the sequences the numbers are held out for: the run's queries, or
                      compare.validation_for's sequences in a validation run
    test_source       what listed them
    pose_reference    kind ("dataset poses" or "pgt"), file (the pose file, or the
                      pattern naming one per frame) and its sha256 (where it is one file)
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from relocfw.core.errors import ConfigError
from relocfw.data.frames import Frame
from relocfw.data.pseudo_ground_truth import frame_key
from relocfw.report.calibration import Calibration

VALIDATION_KEY = "compare.validation_for"
# 7-Scenes' own file names, one pose file beside each colour image.
SEVENSCENES_POSE_FILES = "seq-NN/frame-NNNNNN.pose.txt"


def frame_sequences(frames: Sequence[Frame]) -> list[int] | None:
    """The sorted sequence numbers of frames named as 7-Scenes names them
    (`seq-01/frame-000000`); None when any frame is not (TUM, COLMAP, a folder)."""
    keys = [frame_key(frame.name) for frame in frames]
    if not keys or any(key is None for key in keys):
        return None
    return sorted({key[0] for key in keys if key is not None})


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def pgt_file(dataset: object) -> Path | None:
    """The pseudo-ground-truth file a dataset scores against (dataset.pgt), or None."""
    reference = getattr(dataset, "reference", None)
    path = getattr(reference, "path", None) or getattr(dataset, "pgt", None)
    return None if path is None else Path(path).expanduser()


def pose_reference(dataset: object, frames: Sequence[Frame]) -> dict[str, Any]:
    """kind, file and sha256 of the poses the run was built and scored against."""
    pgt = pgt_file(dataset)
    if pgt is not None:
        return {"kind": "pgt", "file": str(pgt), "sha256": sha256_of(pgt)}
    reference: dict[str, Any] = {"kind": "dataset poses", "file": None, "sha256": None}
    model_file = getattr(dataset, "model_file", None)  # a COLMAP model: one file
    if model_file is not None and Path(model_file).is_file():
        reference |= {"file": str(model_file), "sha256": sha256_of(Path(model_file))}
    elif frames and frame_sequences(frames) is not None:
        scene = frames[0].image_path.parent.parent
        reference["file"] = str(scene / SEVENSCENES_POSE_FILES)
        poses_of = getattr(dataset, "poses_of", None)
        if poses_of is not None:
            reference["poses_of"] = poses_of  # which Kinect sensor they describe
    return reference


def source_of(dataset: object, split: str) -> str | None:
    """What lists a split's frames, as the dataset says (its `split_source`)."""
    describe = getattr(dataset, "split_source", None)
    return None if describe is None else describe(split)


def split_record(
    dataset: object,
    train: Sequence[Frame],
    test: Sequence[Frame],
    calibration: Calibration | None = None,
    validation_for: Sequence[int] | None = None,
) -> dict[str, Any]:
    """The `split` record of a run (see the module).

    Args:
        dataset: the dataset the frames came from (its split_source, pgt file).
        train: the map's frames (the validation block already carved out).
        test: the query frames.
        calibration: the validation block carved from training, or None.
        validation_for: compare.validation_for's test sequences in a validation run
            (checked with `check_validation_run` first), or None.
    """
    query_sequences = frame_sequences(test)
    validation: dict[str, Any] = {}
    if validation_for is not None:
        validation["query_sequences"] = query_sequences
        validation["query_source"] = source_of(dataset, "test")
    if calibration is not None and calibration.frames:
        block = calibration.frames
        validation["calibration_block"] = {
            "frames": len(block),
            "first": block[0].name,
            "last": block[-1].name,
            "sequences": frame_sequences(block),
        }
    return {
        "train_sequences": frame_sequences(train),
        "train_source": source_of(dataset, "train"),
        "validation": validation or None,
        "test_sequences": query_sequences if validation_for is None else list(validation_for),
        "test_source": source_of(dataset, "test")
        if validation_for is None
        else f"{VALIDATION_KEY}={list(validation_for)}",
        "pose_reference": pose_reference(dataset, [*train, *test]),
    }


def numbers(sequences: Sequence[int] | None, source: str | None) -> str:
    """Sequence numbers as a line says them, else what listed the frames."""
    if sequences is not None:
        return ", ".join(str(s) for s in sequences)
    return f"as listed by {source}" if source else "the dataset's split"


def split_line(record: dict[str, Any], scene: str | None = None) -> str:
    """One line for a Markdown report: the sequences and the reference."""
    validation = record["validation"] or {}
    parts = [f"map {numbers(record['train_sequences'], record['train_source'])}"]
    if "query_sequences" in validation:
        parts.append(
            f"validation queries {numbers(validation['query_sequences'], None)} "
            f"(choosing settings for test {numbers(record['test_sequences'], None)})"
        )
    else:
        parts.append(f"test {numbers(record['test_sequences'], record['test_source'])}")
    block = validation.get("calibration_block")
    if block is not None:
        parts.append(
            f"calibration block {block['first']} .. {block['last']} ({block['frames']} frames)"
        )
    reference = record["pose_reference"]
    described = reference["kind"]
    if reference["kind"] == "pgt":
        described += f" {Path(reference['file']).name} (sha256 {reference['sha256'][:12]})"
    elif reference["file"]:
        described += f" ({reference['file']})"
    heading = f"Sequences ({scene})" if scene else "Sequences"
    return f"{heading}: " + "; ".join(parts) + f"; poses: {described}."


def validation_for_option(value: object) -> list[int] | None:
    """compare.validation_for as distinct sequence numbers >= 1, or None (unset)."""
    if value is None:
        return None
    if isinstance(value, (str, bytes, int)) or not isinstance(value, Sequence) or not value:
        raise ConfigError(
            f"{VALIDATION_KEY} must be a list of test sequence numbers such as [5, 6, 7], "
            f"got {value!r}"
        )
    sequences = []
    for item in value:
        if isinstance(item, bool) or not isinstance(item, int) or item < 1:
            raise ConfigError(f"{VALIDATION_KEY}: sequence numbers are integers >= 1, got {item!r}")
        sequences.append(item)
    if len(set(sequences)) != len(sequences):
        raise ConfigError(f"{VALIDATION_KEY} lists a sequence twice: {sequences}")
    return sequences


def check_validation_run(
    dataset: object,
    train: Sequence[Frame],
    test: Sequence[Frame],
    validation_for: Sequence[int],
) -> None:
    """Refuse a validation run whose map or queries use a sequence of the split it
    chooses settings for: settings chosen there would not be held out.

    Raises:
        ConfigError: one line naming the overlapping sequences and what listed them.
    """
    uses = {"map uses": frame_sequences(train), "queries use": frame_sequences(test)}
    if None in uses.values():
        raise ConfigError(
            f"{VALIDATION_KEY} names sequence numbers, but this dataset's frames are not "
            "numbered sequences (seq-NN/frame-NNNNNN): leave it out"
        )
    tested = set(validation_for)
    clashes = [
        f"its {role} {', '.join(map(str, sorted(tested & set(used or ()))))} "
        f"({source_of(dataset, split) or f'the {split} split'})"
        for (role, used), split in zip(uses.items(), ("train", "test"), strict=True)
        if tested & set(used or ())
    ]
    if clashes:
        raise ConfigError(
            f"{VALIDATION_KEY}={list(validation_for)} marks a validation run, but "
            + " and ".join(clashes)
            + ": validation must not touch the test sequences it chooses settings for"
        )
