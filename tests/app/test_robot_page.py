"""docs/robot.md, the robot engineer's first hour: the monocular recipe is one
copy-paste block whose install line holds every extra it needs, and the page names the
files task=localize writes as it goes."""

from __future__ import annotations

import re
from pathlib import Path

from relocfw.app.answer_files import AnswerFiles, partial_of

PAGE = Path(__file__).resolve().parents[2] / "docs" / "robot.md"
BLOCK = re.compile(r"```bash\n(.*?)```", re.DOTALL)
# What each part of the monocular recipe needs installed (pyproject.toml's extras).
NEEDS = {
    "dataset=rosbag": "robot",
    "refine=features_rgb": "structure",
    "preset=real_cpu_quick": "efficientnet",  # EfficientNet-Lite0 from ImageNet
    "task=localize": "onnx",  # engine=auto runs onnxruntime on a CPU
}


def bash_blocks(text: str) -> list[str]:
    return BLOCK.findall(text)


def check_monocular_recipe(text: str) -> None:
    """One bash block builds a map with refine=features_rgb, with the README's preset
    for real images and no depth topic, and localizes; the install line has every
    extra the block needs."""
    recipes = [b for b in bash_blocks(text) if "refine=features_rgb" in b]
    assert len(recipes) == 1, "no single copy-paste block for the monocular recipe"
    (recipe,) = recipes
    assert "preset=real_cpu_quick" in recipe and "crop=centre" in recipe
    assert "depth_topic" not in recipe
    assert "task=localize" in recipe and "task=topics" in recipe
    installs = re.findall(r'pip install [^\n]*-e "\.\[([a-z,]+)\]"', text)
    assert len(installs) == 1, "no single install line with extras"
    extras = set(installs[0].split(","))
    missing = {extra for key, extra in NEEDS.items() if key in recipe} - extras
    assert not missing, f"the install line lacks {sorted(missing)}"


def check_names_the_answer_files(text: str, tmp_path: Path) -> None:
    files = AnswerFiles(tmp_path)
    files.close(finished=True)
    for path in (files.poses_path, files.table_path, files.skipped_path):
        for name in (path.name, partial_of(path).name):
            assert f"`run/{name}`" in text, f"docs/robot.md does not name run/{name}"


def test_the_monocular_recipe_is_one_block_with_every_extra_it_needs():
    check_monocular_recipe(PAGE.read_text())


def test_the_page_names_the_files_localize_writes_as_it_goes(tmp_path):
    check_names_the_answer_files(PAGE.read_text(), tmp_path)
