"""Ctrl-C during a group of queries: raised at once on the calling thread, no thread started."""

import math
import signal
import sys
import threading
import time

import numpy as np
import pytest
import torch

from relocfw import QueryOptions, Relocalizer
from relocfw.core.imaging import image_fingerprint
from relocfw.core.interfaces import CropSearch, crop_at, query_seed
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.posenet import PoseNet

# From the interrupt to the exception in the caller's hands: milliseconds, but the
# suite runs beside other work on 2 cores.
PROMPT_SECONDS = 3.0


def rgb(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (36, 60, 3), dtype=np.uint8)


QUERIES = [rgb(seed) for seed in range(10, 14)]


class InterruptedOnCall(PoseNet):
    """A tiny PoseNet whose `at`-th network pass after `arm()` raises KeyboardInterrupt,
    as Ctrl-C does in the thread that runs the network; every pass is recorded."""

    def __init__(self) -> None:
        torch.manual_seed(0)
        super().__init__(input_size=32, width=0.125, feature_dim=16)
        self.passes: list[str] = []
        self.at: int | None = None
        self.interrupted_at = float("nan")  # perf_counter() of the interrupt

    def arm(self, at: int) -> None:
        self.passes.clear()
        self.at = at

    def record(self, kind: str) -> None:
        self.passes.append(kind)
        if len(self.passes) == self.at:
            self.interrupted_at = time.perf_counter()
            raise KeyboardInterrupt

    def forward(self, images):
        self.record("window")
        return super().forward(images)

    def feature_maps(self, images):
        self.record("strip")
        return super().feature_maps(images)


def fitted(backbone, crop, scoring="plain") -> Relocalizer:
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), crop, QueryOptions(scoring=scoring))
    relocalizer.fit([rgb(seed) for seed in range(4)])
    return relocalizer


@pytest.mark.parametrize(
    "scoring, at", [("plain", 2), ("shared", 1)], ids=["plain-2nd-pass", "shared-strip-pass"]
)
def test_an_interrupt_in_a_network_pass_is_raised_at_once_and_ends_every_search(scoring, at):
    backbone = InterruptedOnCall()
    relocalizer = fitted(backbone, GeneticCropSearch(seed=0), scoring)
    before = threading.active_count()
    backbone.arm(at)
    with pytest.raises(KeyboardInterrupt):
        relocalizer.localize_many(QUERIES, queries_at_once=4)
    assert time.perf_counter() - backbone.interrupted_at < PROMPT_SECONDS
    assert threading.active_count() == before
    # Nothing ran after the interrupted pass: not handed to one query while the others
    # went on searching (shared scoring's strip passes are one query's each).
    assert len(backbone.passes) == at


class SignalsOnFirstQuery(CropSearch):
    """The first query's search sends a real SIGINT to the main thread (Ctrl-C) after
    its first round, then asks again; the other queries' searches only ask."""

    def __init__(self) -> None:
        self.signalled_at = float("nan")  # perf_counter() of the SIGINT
        self.rounds_after = 0  # rounds any search was told after the SIGINT

    def propose(self, query):
        crop = crop_at(0, query.width, query.height)
        yield [crop]
        if math.isnan(self.signalled_at):  # the first search told its distances
            self.signalled_at = time.perf_counter()
            signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)
            time.sleep(0.3)
        else:
            self.rounds_after += 1
        yield [crop_at(query.width - query.height, query.width, query.height)]
        return crop


@pytest.mark.skipif(sys.platform == "win32", reason="pthread_kill is POSIX")
def test_ctrl_c_during_a_groups_search_is_raised_at_once_on_the_calling_thread():
    assert threading.current_thread() is threading.main_thread()
    search = SignalsOnFirstQuery()
    backbone = InterruptedOnCall()
    relocalizer = fitted(backbone, search)
    before = threading.active_count()
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    backbone.arm(at=None)
    try:
        with pytest.raises(KeyboardInterrupt):
            relocalizer.localize_many(QUERIES, queries_at_once=4)
        elapsed = time.perf_counter() - search.signalled_at
    finally:
        signal.signal(signal.SIGINT, previous)
    assert elapsed < PROMPT_SECONDS
    assert threading.active_count() == before
    # The loop stopped where the signal landed: no other search was told its round,
    # and the second round's windows never went through the network.
    assert search.rounds_after == 0 and backbone.passes == ["window"]


class ErrorsByQuery:
    """The search of each query in `errors` (index -> error) raises that error after
    its first round."""

    def __init__(self, errors: dict[int, BaseException]) -> None:
        self.errors = {image_fingerprint(QUERIES[i]): error for i, error in errors.items()}

    def raise_for(self, seed: int) -> None:
        error = self.errors.get(seed)
        if error is not None:
            raise error


class FailsByQuery(ErrorsByQuery, CropSearch):
    """The older, blocking form: the group's queries run one at a time."""

    def search(self, width, height, distance):
        distance([crop_at(0, width, height)])
        self.raise_for(query_seed(distance))
        return crop_at(0, width, height)


class ProposalsFailByQuery(ErrorsByQuery, CropSearch):
    """The ask/tell form: the group's first round is one merged pass, then each
    query is told its distances in turn."""

    def propose(self, query):
        yield [crop_at(0, query.width, query.height)]
        self.raise_for(query.seed)
        return crop_at(0, query.width, query.height)


@pytest.mark.parametrize("form", [FailsByQuery, ProposalsFailByQuery], ids=["search", "propose"])
def test_an_error_in_a_querys_search_ends_the_group_with_the_first_querys_error(form):
    backbone = InterruptedOnCall()
    relocalizer = fitted(backbone, form({0: KeyboardInterrupt()}))
    before = threading.active_count()
    with pytest.raises(KeyboardInterrupt):
        relocalizer.localize_many(QUERIES, queries_at_once=4)
    assert threading.active_count() == before
    # Errors in several queries: the first query's, raised where it happens.
    relocalizer = fitted(backbone, form({2: RuntimeError("later"), 0: ValueError("first")}))
    with pytest.raises(ValueError, match="first"):
        relocalizer.localize_many(QUERIES, queries_at_once=4)
    assert threading.active_count() == before


def test_ctrl_c_ends_the_command_with_one_line_and_status_130(monkeypatch, capsys):
    from relocfw.app import cli

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "hydra_main", interrupted)
    with pytest.raises(SystemExit) as exit_status:
        cli.main()
    assert exit_status.value.code == 130
    assert capsys.readouterr().err.splitlines()[-1] == "interrupted"
