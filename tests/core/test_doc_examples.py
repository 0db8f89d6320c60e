"""Every ```python block of README.md and docs/**/*.md runs, so no example goes stale.

How the blocks run (the convention a page's author follows):

- The blocks of one page run in order in one fresh namespace, so a page can build on
  its earlier blocks; each page starts in an empty temporary working directory, which
  is also on `sys.path`, with `RELOCFW_CACHE` pointing inside it.
- A block whose first line is `# file: PATH` (a file of a plugin package, say) is
  written to PATH under the working directory instead of being run, so later blocks
  can import it. Every `test_*` function a block defines is called after it.
- Examples make their own data through relocfw's public API (e.g. a small
  `relocfw.data.synthetic.SyntheticScene`, a few training steps) and say in a comment
  which settings to use for real. A file that only a command writes (the `.onnx` file
  of `relocfw task=export`) is made by this test instead: `PAGE_INPUTS` names each one
  and the command it stands for.
- Code that is not meant to run (a fragment, a shell session, pseudo code) is not
  tagged python: use ```text (or ```bash).

A block that raises fails the test with the page, the block's number and its line
in the page; the traceback's line numbers are the page's.
"""

from __future__ import annotations

import os
import re
import sys
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PYTHON_INFO = ("python", "py", "python3")  # every name that would highlight as Python
FENCE = re.compile(r"^(?P<indent>\s*)(?P<fence>`{3,}|~{3,})\s*(?P<info>[^`\s]*)")
FILE_HEADER = re.compile(r"^#\s*file:\s*(?P<path>\S+)\s*$")


@dataclass(frozen=True)
class Block:
    """One fenced Python block: its page, its number on the page (from 1), the page
    line of its first code line, and its code."""

    page: str
    number: int
    line: int
    code: str

    @property
    def where(self) -> str:
        return f"{self.page}, python block {self.number} (line {self.line})"


def doc_pages() -> list[Path]:
    """README.md and every page of the docs site."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def python_blocks(path: Path, page: str | None = None) -> list[Block]:
    """The page's ```python blocks, in order; `page` names it in messages (default:
    its path in the repository). Fences are matched as Markdown does: a fence closes
    only with the same character, at least as long, and any other block's content (a
    ```markdown example holding a python fence) is skipped."""
    page = page or str(path.relative_to(ROOT))
    blocks: list[Block] = []
    lines = path.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        opening = FENCE.match(lines[i])
        if opening is None:
            i += 1
            continue
        fence, indent = opening["fence"], len(opening["indent"])
        body, start = [], i + 2  # the page's 1-based line of the first code line
        i += 1
        while i < len(lines):
            closing = FENCE.match(lines[i])
            if (
                closing is not None
                and closing["fence"][0] == fence[0]
                and len(closing["fence"]) >= len(fence)
                and not closing["info"]
            ):
                break
            body.append(lines[i][indent:] if lines[i][:indent].isspace() else lines[i])
            i += 1
        i += 1
        if opening["info"].lower() in PYTHON_INFO:
            blocks.append(Block(page, len(blocks) + 1, start, "\n".join(body) + "\n"))
    return blocks


def onnx_inputs(folder: Path) -> None:
    """docs/onnx.md's robot-side example reads `model.relocfw.onnx` (what `relocfw
    task=export export.model=RUN/model.relocfw` writes) and a camera frame."""
    import cv2
    import numpy as np

    from relocfw.model.onnx_export import export_onnx
    from relocfw.plugins.posenet import PoseNet

    torch_net = PoseNet(input_size=32, width=0.0625, feature_dim=16)
    export_onnx(torch_net, folder / "model.relocfw.onnx")
    frame = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    cv2.imwrite(str(folder / "frame.png"), frame)


# Files a page's examples read that only a command writes: made here, per page.
PAGE_INPUTS: dict[str, Callable[[Path], None]] = {
    "docs/onnx.md": onnx_inputs,
}

PAGES = [path for path in doc_pages() if python_blocks(path)]


def test_the_collector_reads_fences_as_markdown_does(tmp_path: Path) -> None:
    """Only python blocks are collected, a longer fence holding a python fence is
    skipped, and code lines keep the page's line numbers."""
    page = tmp_path / "page.md"
    page.write_text(
        "# t\n\n```python\nx = 1\n```\n\n````markdown\n```python\nraise SystemExit\n```\n"
        "````\n\n- item\n\n    ```python\n    y = x + 1\n    ```\n\n```text\nnot code\n```\n"
    )
    blocks = python_blocks(page, "page.md")
    assert [(b.line, b.code) for b in blocks] == [(4, "x = 1\n"), (16, "y = x + 1\n")]


def test_every_page_with_code_is_collected() -> None:
    """The pages known to hold runnable examples are found, so a change to the
    collector cannot quietly run none."""
    names = {str(path.relative_to(ROOT)) for path in PAGES}
    assert {"docs/python.md", "docs/onnx.md", "docs/plugins.md"} <= names


def run_block(block: Block, namespace: dict, folder: Path) -> None:
    """Write a `# file:` block under `folder`; run any other, then its test_ functions."""
    first = block.code.lstrip("\n").splitlines()[0] if block.code.strip() else ""
    header = FILE_HEADER.match(first)
    if header is not None:
        target = folder / header["path"]
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(block.code)
        return
    before = set(namespace)
    # Blank lines before the code: a traceback names the page's own line numbers.
    code = compile("\n" * (block.line - 1) + block.code, block.page, "exec")
    exec(code, namespace)
    for name in sorted(set(namespace) - before):
        if name.startswith("test_") and callable(namespace[name]):
            namespace[name]()


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_page_examples_run(page: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    name = str(page.relative_to(ROOT))
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("RELOCFW_CACHE", str(tmp_path / "relocfw-cache"))
    if name in PAGE_INPUTS:
        PAGE_INPUTS[name](tmp_path)
    modules = set(sys.modules)
    namespace: dict = {"__name__": f"doc_example_{page.stem}"}
    failure = None
    try:
        for block in python_blocks(page):
            try:
                run_block(block, namespace, tmp_path)
            except Exception:
                failure = f"{block.where} raised:\n{traceback.format_exc()}"
                break
    finally:
        # Modules the page wrote (a plugin package) must not leak into other pages.
        for module in set(sys.modules) - modules:
            origin = getattr(sys.modules[module], "__file__", None) or ""
            if origin.startswith(str(tmp_path) + os.sep):
                del sys.modules[module]
    if failure is not None:
        pytest.fail(failure, pytrace=False)
