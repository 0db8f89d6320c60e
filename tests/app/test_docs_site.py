"""The docs site as a person sees it: built, opened in headless Chromium, offline.

The site is built into a temporary folder (with the mermaid script that
docs/fetch_assets.sh fetches) and every page holding a ```mermaid diagram, the home
page and a results page with figures are opened in Chromium with every host name
unresolvable, as a page opened without a network is. Chromium dumps each page's DOM
after its scripts ran and takes a screenshot. A diagram left as text (its source
still in the visible DOM, not replaced by the drawn diagram) fails the test, naming
the page and the diagram's first line.

Skipped, with the reason, where no Chromium binary is found (Debian: `apt-get install
chromium`), where mkdocs is not installed (`pip install -e ".[docs]"`) or where the
mermaid script cannot be fetched (no npm, or no registry). To look at the
screenshots, set RELOCFW_DOCS_SCREENSHOTS to a folder: they are written there.
"""

from __future__ import annotations

import html
import os
import re
import shutil
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
MERMAID_BLOCK = re.compile(r'<pre class="mermaid"><code>(.*?)</code></pre>', re.S)
IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s]+\.(?:png|svg|jpg|jpeg))\)")
LINKED_FIGURE = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+\.(?:png|svg|jpg|jpeg))\)")
FIGURE_SUFFIXES = (".png", ".svg", ".jpg", ".jpeg")


def chromium() -> str:
    for name in CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    pytest.skip(f"no Chromium binary found ({', '.join(CHROMIUM_NAMES)}): apt-get install chromium")


class VisibleDom(HTMLParser):
    """The text a reader sees (outside script, style and template) and the number of
    drawn diagrams (mkdocs-material's `<div class="mermaid">`, whose SVG lives in a
    closed shadow root that a DOM dump does not show)."""

    HIDDEN = {"script", "style", "template", "noscript"}

    def __init__(self) -> None:
        super().__init__()
        self.hidden_depth = 0
        self.text: list[str] = []
        self.drawn = 0

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        if tag in self.HIDDEN:
            self.hidden_depth += 1
        classes = (dict(attrs).get("class") or "").split()
        if tag == "div" and "mermaid" in classes:
            self.drawn += 1

    def handle_endtag(self, tag: str) -> None:
        if tag in self.HIDDEN and self.hidden_depth:
            self.hidden_depth -= 1

    def handle_data(self, data: str) -> None:
        if not self.hidden_depth:
            self.text.append(data)


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The built site, with the mermaid script fetched into docs/javascripts/."""
    pytest.importorskip("mkdocs", reason='mkdocs is not installed: pip install -e ".[docs]"')
    pytest.importorskip("material", reason='mkdocs-material is not installed: ".[docs]"')
    if shutil.which("npm") is None and not (ROOT / "docs/javascripts/mermaid.min.js").is_file():
        pytest.skip("npm not found: docs/fetch_assets.sh cannot fetch the mermaid script")
    fetched = subprocess.run(
        ["bash", str(ROOT / "docs/fetch_assets.sh")], capture_output=True, text=True, timeout=300
    )
    if fetched.returncode != 0:
        last = (fetched.stderr.strip().splitlines() or ["no output"])[-1]
        pytest.skip(f"docs/fetch_assets.sh could not fetch the mermaid script: {last}")
    folder = tmp_path_factory.mktemp("site")
    built = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--site-dir", str(folder)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert built.returncode == 0, f"mkdocs build failed:\n{built.stderr[-3000:]}"
    return folder


def open_page(page: Path, screenshot: Path, profile: Path) -> str:
    """The page's DOM after its scripts ran (10 s of virtual time), offline; a
    screenshot of its first 1280 x 2400 pixels is written on the way."""
    command = [
        chromium(),
        "--headless",
        "--no-sandbox",  # as root (a container) Chromium refuses to start without it
        "--disable-gpu",
        "--hide-scrollbars",
        f"--user-data-dir={profile}",
        "--host-resolver-rules=MAP * ~NOTFOUND",  # offline: no CDN can stand in
        "--virtual-time-budget=10000",
        "--window-size=1280,2400",
        f"--screenshot={screenshot}",
        "--dump-dom",
        page.as_uri(),
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, f"chromium failed on {page}:\n{done.stderr[-2000:]}"
    return done.stdout


def pages_to_open(site: Path) -> list[Path]:
    """Every page holding a diagram, the home page, and the first results page that
    shows a figure."""
    pages = sorted(site.rglob("*.html"))
    chosen = [p for p in pages if '<pre class="mermaid">' in p.read_text("utf-8")]
    chosen.append(site / "index.html")
    figures = {}  # results page: how far into its article the first figure is
    for page in pages:
        if "results" in page.relative_to(site).parts:
            text = page.read_text("utf-8")
            found = re.search(r'<img [^>]*src="[^"]+\.png"', text)
            if found:
                figures[page] = found.start() - text.find("<article")
    if figures:  # the one whose figure is nearest the top, so the screenshot shows it
        chosen.append(min(figures, key=figures.__getitem__))
    return list(dict.fromkeys(chosen))


def test_the_site_serves_its_mermaid_script(site: Path) -> None:
    script = site / "javascripts" / "mermaid.min.js"
    assert script.is_file() and script.stat().st_size > 100_000, "mermaid.min.js not in the site"
    page = (site / "architecture" / "index.html").read_text("utf-8")
    assert 'src="../javascripts/mermaid.min.js"' in page


def test_diagrams_are_drawn_in_a_browser(site: Path, tmp_path: Path) -> None:
    shots = Path(os.environ.get("RELOCFW_DOCS_SCREENSHOTS") or tmp_path / "screenshots")
    shots.mkdir(parents=True, exist_ok=True)
    pages = pages_to_open(site)
    assert any('<pre class="mermaid">' in p.read_text("utf-8") for p in pages), (
        "no page of the site holds a mermaid diagram: has architecture.md's pipeline moved?"
    )
    problems = []
    for page in pages:
        name = str(page.relative_to(site))
        sources = MERMAID_BLOCK.findall(page.read_text("utf-8"))
        shot = shots / (name.replace("/", "_").removesuffix(".html") + ".png")
        dom = VisibleDom()
        dom.feed(open_page(page, shot, tmp_path / "profile"))
        visible = "".join(dom.text)
        assert shot.is_file() and shot.stat().st_size > 0, f"no screenshot of {name}"
        for source in sources:
            first = html.unescape(source).strip().splitlines()[0]
            if first in visible:
                problems.append(f"{name}: a diagram is left as text ({first!r})")
        if dom.drawn < len(sources):
            problems.append(f"{name}: {dom.drawn} of {len(sources)} diagrams drawn")
    assert not problems, "\n".join(problems)


def test_every_figure_under_docs_is_shown_on_a_page() -> None:
    """A figure committed under docs/ is an image on some page (`![...](...)`), not
    only a link a reader has to click, and every image a page shows exists."""
    docs = ROOT / "docs"
    shown: set[Path] = set()
    linked_only: list[str] = []
    for page in docs.rglob("*.md"):
        text = page.read_text("utf-8")
        for target in IMAGE.findall(text):
            path = (page.parent / target).resolve()
            assert path.is_file(), f"{page.relative_to(ROOT)} shows {target}, which is missing"
            shown.add(path)
        linked_only += [
            f"{page.relative_to(ROOT)}: {target}" for target in LINKED_FIGURE.findall(text)
        ]
    figures = {p.resolve() for p in docs.rglob("*") if p.suffix.lower() in FIGURE_SUFFIXES}
    figures = {p for p in figures if "javascripts" not in p.parts}
    missing = sorted(str(p.relative_to(docs.resolve())) for p in figures - shown)
    assert not missing, (
        "figures under docs/ that no page shows as an image: "
        + ", ".join(missing)
        + (" (linked only: " + "; ".join(linked_only) + ")" if linked_only else "")
    )
