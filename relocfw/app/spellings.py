"""Old option spellings, read as their new keys with one note each.

Query options moved into `query.*`, task=localize's into `localize.*`, and so on
(conf/config.yaml). Command lines, scripts and methods files written before still
work: each old key is rewritten to its new one before Hydra parses it, and one line on
stderr says so. Only the key changes; the value (a multirun list such as
`scoring=plain,shared` too) and the prefix (`+`, `++`, `~`) stay as written.

An option that became something a key cannot follow is refused instead, in one line
giving the new spelling: `query.retrieval_k=K` (and the older `retrieval_k=K`) is the
refiner `refine=retrieval refine.k=K` now, two overrides where there was
one, and `refine=` may already be set otherwise on the same line.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

from relocfw.core.errors import ConfigError

# Old top-level key -> new key; `model` depends on the task (see new_key).
MOVED = {
    "query_batch_size": "query.batch_size",
    "queries_at_once": "query.queries_at_once",
    "scoring": "query.scoring",
    "rerank": "query.rerank",
    "crop_samples": "query.crop_samples",
    "images": "localize.images",
    "backend": "engine",
    "localize.backend": "engine",
    "baselines": "relocalize.baselines",
    "pretrained_required": "train.pretrained_required",
}
MODEL_KEYS = {"localize": "localize.model", "export": "export.model"}
OLD_KEYS = (*MOVED, "model")
# Keys refused with their new spelling (see the module's docstring).
REMOVED = ("retrieval_k", "query.retrieval_k")
OVERRIDE = re.compile(r"(?P<prefix>~|\+\+|\+)?(?P<key>[A-Za-z_][\w.]*)(?P<rest>=.*)?", re.S)


@dataclass(frozen=True)
class Rewrite:
    """One old key found in a list of overrides: what it became, as written."""

    old: str
    new: str
    read_as: str

    def note(self, where: str = "") -> str:
        context = f"{where}: " if where else ""
        return f"note: {self.old}= is now {self.new}= ({context}read as {self.read_as})"


def task_of(overrides: Sequence[str], default: str = "relocalize") -> str:
    """The task a list of overrides runs (its last `task=`), for `model=`."""
    task = default
    for override in overrides:
        match = OVERRIDE.fullmatch(override)
        if match and match["key"] == "task" and match["rest"] and match["prefix"] != "~":
            task = match["rest"][1:].strip()
    return task


def new_key(old: str, task: str) -> str:
    if old == "model":
        return MODEL_KEYS.get(task, "localize.model")
    return MOVED[old]


def rewrite(overrides: Sequence[str], task: str | None = None) -> tuple[list[str], list[Rewrite]]:
    """`overrides` with every old key spelled anew, and what was rewritten (one entry
    per old key, its last use).

    Args:
        overrides: Hydra overrides (`key=value`, `+key=value`, `~key`); anything else
            (flags such as `-m`, `--help`) is kept as it is.
        task: the task they run, which decides where `model=` goes; None: their own
            `task=`, else relocalize.

    Raises:
        ConfigError: a REMOVED key, with its new spelling.
    """
    task = task_of(overrides) if task is None else task
    out: list[str] = []
    found: dict[str, Rewrite] = {}
    for override in overrides:
        match = OVERRIDE.fullmatch(override)
        if match is not None and match["key"] in REMOVED:
            refuse_removed(override, match)
        if match is None or match["key"] not in OLD_KEYS:
            out.append(override)
            continue
        if match["rest"] is None and match["prefix"] != "~":
            out.append(override)  # a bare word (a flag's argument), not an override
            continue
        key = new_key(match["key"], task)
        spelled = f"{match['prefix'] or ''}{key}{match['rest'] or ''}"
        out.append(spelled)
        found[match["key"]] = Rewrite(match["key"], key, spelled)
    return out, list(found.values())


def refuse_removed(override: str, match: re.Match[str]) -> None:
    """ConfigError for a REMOVED key, saying what to write instead; a bare word (a
    flag's argument) passes."""
    if match["rest"] is None and match["prefix"] != "~":
        return
    value = (match["rest"] or "=")[1:].strip()
    # ~key (deleting it), key=null (the old default) and key=0 all meant no retrieval.
    if match["prefix"] == "~" or value.lower() in ("", "0", "null", "none"):
        instead = "drop it (refine=none, the default, answers with the network's pose)"
    else:
        instead = f"write refine=retrieval refine.k={value}"
    raise ConfigError(
        f"{override}: {match['key']} is no longer an option; the image-retrieval baseline "
        f"is a refiner now: {instead}"
    )
