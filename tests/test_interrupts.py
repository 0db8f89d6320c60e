"""Ctrl-C during a group of queries: raised at once, no search thread left behind."""

import signal
import sys
import threading
import time

import numpy as np
import pytest
import torch

from relocfw import Relocalizer
from relocfw.core.imaging import image_fingerprint
from relocfw.core.interfaces import CropSearch, crop_at, query_seed
from relocfw.core.lockstep import Lockstep
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
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), crop, scoring=scoring)
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


def main_thread_waits_in_serve() -> bool:
    """True while the main thread is blocked in a wait inside Lockstep.serve."""
    frame = sys._current_frames().get(threading.main_thread().ident)
    names = []
    while frame is not None:
        names.append(frame.f_code.co_name)
        frame = frame.f_back
    return names[:1] == ["wait"] and "serve" in names


class FirstSearchSignals(CropSearch):
    """The first search to start waits until the serving thread waits for it, then sends
    a real SIGINT to the main thread (Ctrl-C) before it asks; the others ask at once."""

    def __init__(self) -> None:
        self.first = threading.Lock()
        self.signalled_at = float("nan")  # perf_counter() of the SIGINT

    def search(self, width, height, distance):
        if self.first.acquire(blocking=False):
            deadline = time.perf_counter() + 30
            while not main_thread_waits_in_serve() and time.perf_counter() < deadline:
                time.sleep(0.01)
            self.signalled_at = time.perf_counter()
            signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)
            time.sleep(0.3)
        distance([crop_at(0, width, height)])
        return crop_at(0, width, height)


@pytest.mark.skipif(sys.platform == "win32", reason="pthread_kill is POSIX")
def test_ctrl_c_while_the_serving_thread_waits_leaves_no_thread_blocked():
    assert threading.current_thread() is threading.main_thread()
    search = FirstSearchSignals()
    relocalizer = fitted(InterruptedOnCall(), search)
    before = threading.active_count()
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            relocalizer.localize_many(QUERIES, queries_at_once=4)
        elapsed = time.perf_counter() - search.signalled_at
    finally:
        signal.signal(signal.SIGINT, previous)
    assert elapsed < PROMPT_SECONDS
    assert threading.active_count() == before


class FailsByQuery(CropSearch):
    """The search of each query in `errors` (index -> error) raises that error."""

    def __init__(self, errors: dict[int, BaseException]) -> None:
        self.errors = {image_fingerprint(QUERIES[i]): error for i, error in errors.items()}

    def search(self, width, height, distance):
        distance([crop_at(0, width, height)])
        error = self.errors.get(query_seed(distance))
        if error is not None:
            raise error
        return crop_at(0, width, height)


def test_an_interrupt_in_one_query_wins_over_an_ordinary_error_in_another():
    ordinary = ValueError("an ordinary failure")
    relocalizer = fitted(InterruptedOnCall(), FailsByQuery({0: ordinary, 1: KeyboardInterrupt()}))
    before = threading.active_count()
    with pytest.raises(KeyboardInterrupt):
        relocalizer.localize_many(QUERIES, queries_at_once=4)
    assert threading.active_count() == before
    # Ordinary errors alone: still the first query's, whatever the timing.
    relocalizer.crop = FailsByQuery({2: RuntimeError("later"), 0: ordinary})
    with pytest.raises(ValueError, match="ordinary"):
        relocalizer.localize_many(QUERIES, queries_at_once=4)


def test_a_cancelled_lockstep_releases_waiting_members_and_refuses_later_asks():
    from relocfw.core.lockstep import Cancelled  # here: the old code lacks it

    lockstep = Lockstep(2, lambda requests: list(requests))
    outcome = {}

    def member():
        try:
            lockstep.ask(0, "waits for member 1, which never asks")
        except Cancelled:
            outcome["cancelled"] = True

    thread = threading.Thread(target=member)
    thread.start()
    time.sleep(0.1)
    lockstep.cancel()
    thread.join(PROMPT_SECONDS)
    assert outcome == {"cancelled": True} and not thread.is_alive()
    with pytest.raises(Cancelled):
        lockstep.ask(1, "too late")


def test_ctrl_c_ends_the_command_with_one_line_and_status_130(monkeypatch, capsys):
    from relocfw.app import cli

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "hydra_main", interrupted)
    with pytest.raises(SystemExit) as exit_status:
        cli.main()
    assert exit_status.value.code == 130
    assert capsys.readouterr().err.splitlines()[-1] == "interrupted"
