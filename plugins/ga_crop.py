"""The paper's genetic algorithm over the crop offset.

A chromosome is the offset in n bits, 2^(n-1) <= span < 2^n (the paper's
2^(n-1) < span < 2^n, with the larger n where span is a power of two), decoded as
round(dec / (2^n - 1) * span): all-zeros and all-ones reach both edges and, since
2^n - 1 >= span, every offset in between is the decode of some chromosome.
Fitness is exp(-distance); parents are drawn by roulette, paired for single-point
crossover with probability Pc, and each bit flips with probability Pm.

Each query draws its own random stream from the search's seed and the query's seed
(a fingerprint of the image, see relocfw.core.interfaces.SearchQuery): a test
split is many independent GA runs, not one run repeated, and the same image still
gives the same crop.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from relocfw.core.interfaces import (
    CropProposals,
    CropSearch,
    SearchQuery,
    crop_at,
    crop_side_and_span,
)
from relocfw.core.options import integer_at_least, probability


def chromosome_bits(span: int) -> int:
    """Bits n with 2^(n-1) <= span < 2^n, so 2^n - 1 >= span and no offset is unreachable.

    A span of 256 (1024 x 768 images) needs 9 bits: with 8, 255 codes cannot reach
    257 offsets and some, the centre among them, could never be chosen.
    """
    return max(1, int(span).bit_length())


def offset_of(values: np.ndarray | int, bits: int, span: int) -> np.ndarray:
    """Offsets of chromosomes given as integers: round(value / (2^bits - 1) * span).

    np.rint rounds halves to even, as Python's round does.
    """
    return np.rint(np.asarray(values) / (2**bits - 1) * span).astype(np.int64)


def decode(chromosome: Sequence[int], span: int) -> int:
    """Offset in pixels of a binary chromosome (most significant bit first)."""
    value = int("".join(str(int(b)) for b in chromosome), 2)
    return int(offset_of(value, len(chromosome), span))


def roulette(fitness: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Indices drawn with probability proportional to fitness."""
    total = fitness.sum()
    if not np.isfinite(total) or total <= 0:
        return rng.integers(0, len(fitness), size=count)
    return rng.choice(len(fitness), size=count, p=fitness / total)


class GeneticCropSearch(CropSearch):
    """Genetic search for the crop whose descriptor is closest to the map.

    Args:
        population: individuals per generation (paper: 10).
        crossover: probability Pc that a parent pair exchanges tails (paper: 0.8).
        mutation: probability Pm that each bit flips (paper: 0.1).
        iterations: generations bred after the initial one (paper: 3), so at most
            population * (iterations + 1) crops are scored.
        seed: the search's seed; each query's stream is drawn from it and the query's
            seed, so the same image gives the same crop.

    An ask/tell search: each generation's new offsets are one batch (`propose`).
    """

    def __init__(
        self,
        population: int = 10,
        crossover: float = 0.8,
        mutation: float = 0.1,
        iterations: int = 3,
        seed: int = 0,
    ) -> None:
        self.population = integer_at_least("population", population, 2)
        self.crossover = probability("crossover", crossover)
        self.mutation = probability("mutation", mutation)
        self.iterations = integer_at_least("iterations", iterations, 0)
        self.seed = integer_at_least("seed", seed, 0)

    def propose(self, query: SearchQuery) -> CropProposals:
        width, height = query.width, query.height
        _, span = crop_side_and_span(width, height)
        if span == 0:
            return crop_at(0, width, height)
        rng = np.random.default_rng([self.seed, query.seed])
        bits = chromosome_bits(span)
        weights = 2 ** np.arange(bits - 1, -1, -1)  # most significant bit first
        scores: dict[int, float] = {}  # offset -> distance; an offset is scored once
        chromosomes = rng.integers(0, 2, size=(self.population, bits))
        for generation in range(self.iterations + 1):
            offsets = offset_of(chromosomes @ weights, bits, span).tolist()
            new = list(dict.fromkeys(o for o in offsets if o not in scores))
            if new:
                values = yield [crop_at(o, width, height) for o in new]
                scores.update(zip(new, (float(v) for v in values), strict=True))
            distances = np.array([scores[o] for o in offsets])
            if generation == self.iterations:
                break
            # exp(-(d - min d)) has the same proportions as exp(-d) without underflow.
            fitness = np.exp(-(distances - distances.min()))
            chromosomes = self._breed(chromosomes, fitness, rng)
        best = min(scores, key=lambda o: (scores[o], o))
        return crop_at(best, width, height)

    def _breed(
        self, parents: np.ndarray, fitness: np.ndarray, rng: np.random.Generator
    ) -> np.ndarray:
        children = parents[roulette(fitness, len(parents), rng)].copy()
        bits = children.shape[1]
        for i in range(0, len(children) - 1, 2):
            if bits > 1 and rng.random() < self.crossover:
                cut = rng.integers(1, bits)
                tail = children[i, cut:].copy()
                children[i, cut:] = children[i + 1, cut:]
                children[i + 1, cut:] = tail
        flips = rng.random(children.shape) < self.mutation
        return np.where(flips, 1 - children, children)
