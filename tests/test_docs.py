"""The documentation: README.md and docs/*.md stay user documentation.

The README stays short, no page narrates how the work went, every relative link points to a
file (and heading) that exists, the README's quick start is what CI runs, and the README's
results table quotes docs/benchmarks.md, which the benchmark scripts write.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS]

# Phrases of a lab notebook, not of documentation (compared case-insensitively).
WORK_HISTORY = ("stop 1", "scratch run", "used to be", "this stop", "old default")

_LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
_FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    s = heading.strip().lower()
    s = re.sub(r"[^\w\- ]", "", s)
    return s.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    text = _FENCE.sub("", path.read_text())
    return {_slug(m.group(1)) for m in re.finditer(r"^#{1,6}\s+(.+?)\s*#*\s*$", text, re.M)}


def test_readme_under_200_lines():
    n = len(README.read_text().splitlines())
    assert n < 200, f"README.md has {n} lines; keep it under 200 (details go to docs/)"


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_no_work_history(page):
    text = page.read_text().lower()
    found = [p for p in WORK_HISTORY if p in text]
    assert not found, f"{_rel(page)} narrates work history: {found}"


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_relative_links_resolve(page):
    text = _FENCE.sub("", page.read_text())
    bad = []
    for target in _LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        file_part, _, anchor = target.partition("#")
        dest = page if not file_part else (page.parent / file_part).resolve()
        if not dest.exists():
            bad.append(f"{target} (no such file)")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            bad.append(f"{target} (no such heading)")
    assert not bad, f"{_rel(page)}: broken links: {bad}"


def test_sources_cite_no_missing_files_or_history():
    """Docstrings and comments explain and cite what is in the repository: no work history,
    no files that are not here (``MEASUREMENTS.md``) and no modules that do not exist."""
    phrases = (*WORK_HISTORY, "measurements.md", "jaxrefl.infer")
    bad = []
    for path in sorted((ROOT / "jaxrefl").rglob("*.py")):
        text = path.read_text().lower()
        bad += [f"{_rel(path)}: {p!r}" for p in phrases if p in text]
    assert not bad, bad


def test_docs_pages_exist():
    for name in ("architecture.md", "glossary.md", "benchmarks.md"):
        assert (ROOT / "docs" / name).is_file(), name


def test_quick_start_is_what_ci_runs():
    """The two quick-start commands of the README are the two commands .ci/run runs."""
    readme = README.read_text()
    block = re.search(r"## Install and quick start.*?```bash\n(.*?)```", readme, re.S)
    assert block, "README.md: no bash block under '## Install and quick start'"
    commands = [ln.strip() for ln in block.group(1).splitlines() if ln.strip()]
    ci = [
        ln.strip()
        for ln in (ROOT / ".ci" / "run").read_text().splitlines()
        if ln.strip().startswith("python3.11 -m pip install")
    ]
    assert commands == ci, f"README quick start {commands} != .ci/run {ci}"


def test_results_link_to_benchmarks_md_and_copy_no_figure():
    """The README's results point at docs/benchmarks.md, which the benchmark scripts write;
    the README copies none of its figures (a copied figure goes stale when a script reruns)."""
    readme = README.read_text()
    section = re.search(r"^## Results\n(.*?)(?=^## )", readme, re.S | re.M)
    assert section, "README.md: no '## Results' section"
    text = section.group(1)
    assert "docs/benchmarks.md" in text
    assert not re.findall(r"\b\d+\.\d+\b", text), "README.md: a figure copied into Results"


def test_readme_prose_copies_no_figure():
    """Outside code, the README states no decimal figure: a measurement lives in
    docs/benchmarks.md and a default's value in its code (both go stale when copied); the
    Python version of the quick start aside."""
    text = re.sub(r"`[^`]*`", "", _FENCE.sub("", README.read_text()))  # code: inline too
    found = [x for x in re.findall(r"(?<![\w.])\d+\.\d+(?![\w.])", text) if x != "3.11"]
    assert not found, f"README.md: figures copied outside code: {found}"
