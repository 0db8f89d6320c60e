"""QueryOptions: how the pipeline localizes a query, one validated value.

What a model file stores besides its plugins, what `task=localize` overrides key by
key (`query.*=null` keeps the file's value), and what `Relocalizer` reads. Checks that
need only the options run once, here; those that need the backbone or the refiner
(shared scoring needs a backbone with feature maps; sampling cannot go with a refiner
that replaces the network's pose) run when a Relocalizer is built
(relocfw.core.pipeline.check_options).

The image-retrieval baseline is the refiner `refine=retrieval`, not a query option
(relocfw.plugins.retrieval_refiner.RetrievalRefiner).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from relocfw.core.errors import ConfigError
from relocfw.core.imaging import MAX_ASPECT
from relocfw.core.options import integer_at_least, real_number

SCORINGS = ("plain", "shared", "scout")
# Scorings whose distances only rank candidates: the chosen crop is then scored plainly.
RANKING_SCORINGS = ("shared", "scout")
# The most distinct candidate windows a query's crop search may ask to score. A sweep
# (crop=sweep, crop=rule) asks for every window along the long side: (aspect - 1) x
# the window side + 1, so 2305 for the thinnest image MAX_ASPECT lets through with a
# 224 network trained at crop_scale 256/224 (a 640 x 480 frame: 86). 4096 keeps every
# search's answers on such images, and bounds a query at about 50 times a frame's work.
MAX_CANDIDATES = 4096
# Options that left QueryOptions, and where they went (one clear refusal, not "unknown").
MOVED_OUT = {
    "retrieval_k": "the retrieval baseline is a refiner now: refine=retrieval refine.k=K "
    "(in Python: Relocalizer(..., refiner=RetrievalRefiner(k=K)), "
    "relocfw.plugins.retrieval_refiner)",
}


# Keyword-only: a field removed or added (retrieval_k became refine=retrieval) must not
# shift a positional caller's values onto other options.
@dataclass(frozen=True, kw_only=True)
class QueryOptions:
    """How a query is localized; every field has the paper's behaviour as its default.

    Args:
        batch_size: most crops per forward pass (and map images when fitting).
        scoring: how candidate crops are scored. "plain": each distinct window goes
            through the whole network (the paper). "shared": the trunk runs once over
            the whole strip and every candidate is pooled from its maps
            (relocfw.core.window_pooling); the chosen crop then goes through the plain
            path once, so the pose is the plain pose of that crop. Needs a backbone
            with `feature_maps` and `describe_pooled`. "scout": every distinct window
            goes through the backbone's scout (`Backbone.scout_features`: with
            engine=onnx and onnx.int8, the int8 graph), a cheaper approximate copy of
            the network; the chosen crop then goes through the plain network once, so
            the pose is the float32 one of the crop the scout chose.
        rerank: with scoring="shared" or "scout", the `rerank` windows with the
            smallest such distances (the search's choice among them) go through the
            plain network in one batch and the smallest plain distance chooses. 1: the
            search's choice.
        crop_samples: > 0 answers with the mean pose of this many random windows of the
            chosen crop (test-time crop sampling, relocfw.core.sampling); with the
            backbone's Monte Carlo dropout on, each window gets its own mask. Needs a
            model trained with crop_scale > 1 (else every window is the same).
        sample_seed: seeds the samples, mixed with each query image's fingerprint.
        queries_at_once: how many queries of a list (`localize_many`, a test split)
            are searched together, their windows in merged forward passes; the answers
            are the same. 1: one at a time, so each query's `seconds` is its latency.
        max_aspect: the thinnest query image answered: its long side at most this
            many times its short side (relocfw.core.imaging.MAX_ASPECT); a thinner
            one is refused with a DataError. The strip's memory and a sweep's windows
            grow with this ratio. Answers are unchanged.
        max_candidates: the most distinct windows a query's crop search may ask to
            score (every crop search); past it the query is refused with a DataError
            before any is scored. Answers are unchanged.

    Raises:
        ConfigError: naming the option, for a wrong type, range or combination.
    """

    batch_size: int = 16
    scoring: str = "plain"
    rerank: int = 1
    crop_samples: int = 0
    sample_seed: int = 0
    queries_at_once: int = 1
    max_aspect: float = MAX_ASPECT
    max_candidates: int = MAX_CANDIDATES

    def __post_init__(self) -> None:
        # Frozen: the checked (int) values replace what was given, once.
        for name, least in (
            ("batch_size", 1),
            ("rerank", 1),
            ("crop_samples", 0),
            ("sample_seed", 0),
            ("queries_at_once", 1),
            ("max_candidates", 1),
        ):
            object.__setattr__(self, name, integer_at_least(name, getattr(self, name), least))
        if isinstance(self.max_aspect, bool):
            raise ConfigError(f"max_aspect must be a number, got {self.max_aspect!r}")
        max_aspect = real_number("max_aspect", self.max_aspect)
        if max_aspect < 1:
            raise ConfigError(f"max_aspect must be at least 1 (a square), got {self.max_aspect!r}")
        object.__setattr__(self, "max_aspect", max_aspect)
        if self.scoring not in SCORINGS:
            raise ConfigError(f"scoring must be one of {', '.join(SCORINGS)}, got {self.scoring!r}")
        if self.rerank > 1 and self.scoring not in RANKING_SCORINGS:
            raise ConfigError(
                f"rerank={self.rerank} re-scores the best shared- or scout-scoring "
                f"candidates plainly; with scoring={self.scoring} every candidate is "
                "already plain (use scoring=shared or scoring=scout)"
            )

    def replace(self, **changes: Any) -> QueryOptions:
        """These options with some changed (checked again); None keeps a value."""
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})

    def as_dict(self) -> dict[str, Any]:
        """Plain values, as a model file stores them."""
        return dataclasses.asdict(self)

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], where: str = "query") -> QueryOptions:
        """Options from a mapping (a model file's, a config group's); None = default.

        Raises:
            ConfigError: an unknown key (named with `where`), or a bad value.
        """
        known = {field.name for field in dataclasses.fields(cls)}
        moved = sorted(set(values) & set(MOVED_OUT))
        if moved:
            name = moved[0]
            raise ConfigError(f"{where}: {name} is no longer a query option; {MOVED_OUT[name]}")
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(
                f"{where}: unknown option(s) {', '.join(unknown)}; "
                f"known: {', '.join(sorted(known))}"
            )
        return cls(**{k: v for k, v in values.items() if v is not None})
