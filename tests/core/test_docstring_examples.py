"""The examples in the public docstrings run as written (kornia's habit: an example
that drifts from the code fails here, not in a user's hands).

Every module of relocfw whose docstrings hold a `>>>` example is collected from the
source, so a new example is checked without being listed; examples marked
`# doctest: +SKIP` (they need a trained network or a running server) are skipped by
doctest itself.
"""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

import relocfw

PACKAGE = Path(relocfw.__file__).parent


def modules_with_examples() -> list[str]:
    names = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if "__pycache__" in path.parts or ">>> " not in path.read_text():
            continue
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


def test_some_module_holds_an_example():
    # Guards the collection itself: a wrong path would otherwise pass with no example.
    assert "relocfw.core.interfaces" in modules_with_examples()


@pytest.mark.parametrize("name", modules_with_examples())
def test_the_docstring_examples_run(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS, verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"
