"""One plain loop that runs the crop searches of a group of queries together.

Each ask/tell search (`CropSearch.propose`) yields a batch of crops and waits to be
sent their distances. A round collects what every unfinished query asks, scores the
new plain windows of all of them in one merged forward pass (split into `batch_size`
chunks), sends each query its distances, and goes on until every search has named its
crop. No threads: an error is raised where it happens, and Ctrl-C stops the loop at
once. Shared scoring pools each query from its own strip's maps, query by query;
scout scoring merges the queries' windows as plain scoring does.

A search that only defines the older `search(width, height, distance)` blocks inside
`distance`, so its queries run one at a time.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from relocfw.core.errors import RelocfwError
from relocfw.core.interfaces import CropProposals, CropSearch
from relocfw.core.query_windows import QueryWindows
from relocfw.core.scorer import Scorer
from relocfw.core.values import Crop


def search_together(search: CropSearch, queries: Sequence[QueryWindows]) -> list[Crop]:
    """The crop each query's search chooses, the group's plain windows scored together."""
    if not search.asks_and_tells:
        return [
            checked(search, search.search(q.image.shape[1], q.image.shape[0], q), q)
            for q in queries
        ]
    proposals: dict[int, CropProposals] = {}
    asked: dict[int, list] = {}  # query -> the corners of the crops it asked for
    chosen: dict[int, Crop] = {}

    def advance(member: int, values: object) -> None:
        """Send `values` (None: start) and keep what the search asks next or chose."""
        try:
            crops = next(proposals[member]) if values is None else proposals[member].send(values)
        except StopIteration as end:
            chosen[member] = checked(search, end.value, queries[member])
            asked.pop(member, None)
            return
        asked[member] = queries[member].corners(crops)

    for member, query in enumerate(queries):
        proposals[member] = search.propose(query.search_query())
        advance(member, None)
    while asked:
        score_round(queries, asked)
        for member, corners in list(asked.items()):
            query = queries[member]
            # A search that sees answers gets each crop's pose beside its distance.
            advance(
                member, query.scores(corners) if search.sees_answers else query.distances(corners)
            )
    return [chosen[member] for member in range(len(queries))]


def score_chosen_together(
    queries: Sequence[QueryWindows], crops: Sequence[Crop], rerank: int
) -> None:
    """The plain windows every query's answer needs after its search (its chosen crop's
    and, with shared or scout scoring, its rerank candidates), in merged forward passes."""
    pairs = enumerate(zip(queries, crops, strict=True))
    needed = {member: query.rerank_candidates(crop, rerank) for member, (query, crop) in pairs}
    score_plain_together(queries, needed)


def score_round(queries: Sequence[QueryWindows], asked: dict[int, list]) -> None:
    """Score every window asked for this round that its query has not scored yet."""
    plain: dict[int, list] = {}
    scout: dict[int, list] = {}
    for member, corners in asked.items():
        scoring = queries[member].scoring
        if scoring == "shared":  # each query from its own strip's maps
            queries[member].score_ranking(corners)
        elif scoring == "scout":
            scout[member] = corners
        else:
            plain[member] = corners
    score_plain_together(queries, plain)
    score_scout_together(queries, scout)


def score_plain_together(queries: Sequence[QueryWindows], wanted: dict[int, list]) -> None:
    """Plain windows of several queries, those not scored yet, in one merged pass."""
    score_merged(
        queries,
        wanted,
        QueryWindows.unscored,
        lambda scorer, requests: scorer.plain_together(requests),
        QueryWindows.keep_plain,
    )


def score_scout_together(queries: Sequence[QueryWindows], wanted: dict[int, list]) -> None:
    """Scout windows of several queries, those not scored yet, in one merged pass."""
    score_merged(
        queries,
        wanted,
        QueryWindows.unranked,
        lambda scorer, requests: scorer.scout_together(requests),
        QueryWindows.keep_ranking,
    )


def score_merged(
    queries: Sequence[QueryWindows],
    wanted: dict[int, list],
    new_of: Callable[[QueryWindows, list], list],
    score: Callable[[Scorer, list], list],
    keep: Callable[[QueryWindows, list, Any], None],
) -> None:
    """The windows in `wanted` (query -> corners) that `new_of` says a query lacks,
    scored by `score(scorer, requests)` in one merged call and split back to each query
    by `keep`. `score` looks the method up on the scorer when it runs, so a wrapped
    scorer method (a benchmark's timer, a test's recorder) is the one called."""
    new = {m: corners for m, asked in wanted.items() if (corners := new_of(queries[m], asked))}
    if not new:
        return
    scorer = queries[next(iter(new))].scorer
    scored = score(scorer, [(queries[m].strip, corners) for m, corners in new.items()])
    for (member, corners), result in zip(new.items(), scored, strict=True):
        keep(queries[member], corners, result)


def checked(search: CropSearch, crop: object, query: QueryWindows) -> Crop:
    """The search's choice if it is a crop of the query image; RelocfwError if not."""
    height, width = query.image.shape[:2]
    if not isinstance(crop, Crop):
        raise RelocfwError(
            f"crop search {type(search).__name__} chose {crop!r}, not a relocfw Crop"
        )
    side = min(width, height)
    if crop.size != side or not (0 <= crop.x <= width - side and 0 <= crop.y <= height - side):
        raise RelocfwError(
            f"crop search {type(search).__name__} chose {crop}, which is not a "
            f"{side} x {side} square inside the {width} x {height} image"
        )
    return crop
