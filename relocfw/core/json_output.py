"""Result files as strict JSON, which every parser reads (not Python's NaN/Infinity)."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np


def json_ready(value: Any) -> Any:
    """NaN (undefined) becomes null, an infinite error (a failed query) "inf" or "-inf"."""
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_ready(v) for v in value]
    if isinstance(value, float | np.floating):
        if math.isnan(value):
            return None
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return float(value)
    if isinstance(value, np.integer):
        return int(value)
    return value


def strict_json(value: Any) -> str:
    """Indented strict JSON text with a final newline; refuses anything json_ready missed."""
    return json.dumps(json_ready(value), indent=2, allow_nan=False) + "\n"
