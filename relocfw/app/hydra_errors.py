"""Hydra's and OmegaConf's composition errors as one line.

Hydra reports a bad override over several lines (the error, the OmegaConf cause with
its full_key and object types, the config search path, a hint about
HYDRA_FULL_ERROR); a relocfw command ends with one line that names the key.
"""

from __future__ import annotations

import re

from hydra.errors import HydraException, MissingConfigException
from omegaconf.errors import OmegaConfBaseException

COMPOSITION_ERRORS = (HydraException, OmegaConfBaseException)
MERGING_OVERRIDE = re.compile(r"Error merging override (?P<override>.+)")


def lines_of(error: BaseException) -> list[str]:
    return [line.strip() for line in str(error).splitlines() if line.strip()]


def first_line(error: BaseException) -> str:
    lines = lines_of(error)
    return lines[0] if lines else type(error).__name__


def available_options(text: str) -> str:
    """'available options in 'crop': centre, ga, sweep' from a MissingConfigException."""
    match = re.search(r"(Available options in '[^']*'):\n((?:\t.*\n?)*)", text)
    if not match:
        return ""
    options = [line.strip() for line in match[2].splitlines() if line.strip()]
    return f"{match[1].lower()}: {', '.join(options)}" if options else ""


def one_line(error: BaseException) -> str:
    """The error in one line: the override (or key) it is about, what is wrong, and
    Hydra's hint in brackets."""
    head = first_line(error)
    cause = error.__cause__
    if isinstance(error, MissingConfigException):
        # The rest is the search path: the options are what a user needs.
        options = available_options(str(error))
        return f"{head} ({options})" if options else head
    if isinstance(error, OmegaConfBaseException):
        # OmegaConf's further lines are full_key and the object types.
        key = getattr(error, "full_key", None)
        return f"{key}: {head}" if key and not head.startswith(str(key)) else head
    merging = MERGING_OVERRIDE.fullmatch(head)
    if merging and cause is not None:
        return f"{merging['override']}: {first_line(cause)}"
    text = head.rstrip(".")
    if isinstance(cause, OmegaConfBaseException):
        text += f": {first_line(cause)}"
    hints = lines_of(error)[1:]
    return f"{text} ({'; '.join(hints)})" if hints else text
