"""The README is a door and the docs are the house: what they name must exist.

Every relative link resolves (anchors included), every ``make`` target the README names is in the
Makefile, every ``posediff <command>`` is a real command, every ``+experiment=NAME`` has its file,
and every backticked repository path exists (a ``<placeholder>`` or ``*`` matches by glob).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from posediff.cli import COMMANDS
from posediff.cli.main import DATA_COMMANDS

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS]
MAX_README_LINES = 250

LINK = re.compile(r"\]\(([^)\s]+)\)")
CODE = re.compile(r"`([^`\n]+)`")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)
# files docs/extending.md tells the reader to write: examples, not parts of the repository
TO_BE_WRITTEN = {"conf/sampler/mine.yaml", "conf/group/so2.yaml", "conf/data/mine.yaml"}
REPO_TOP = ("src/", "conf/", "tests/", "benchmarks/", "notebooks/", "docs/", ".ci/")


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces → hyphens."""
    text = heading.strip().lstrip("#").strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text())
    return {_slug(line) for line in text.splitlines() if re.match(r"^#{1,6} ", line)}


def _name(page: Path) -> str:
    return str(page.relative_to(ROOT))


def test_readme_is_a_door() -> None:
    lines = README.read_text().splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines; move sections into docs/"
    text = README.read_text()
    for needed in ("make demo", "make test", "## Command line", "## Results", "docs/architecture.md"):
        assert needed in text, f"README.md lacks {needed!r}"


@pytest.mark.parametrize("page", PAGES, ids=_name)
def test_relative_links_resolve(page: Path) -> None:
    broken = []
    for target in LINK.findall(FENCE.sub("", page.read_text())):
        if target.startswith(("http://", "https://", "mailto:")) or "(" in target:
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            broken.append(target)
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(target)
    assert not broken, f"{_name(page)}: broken links {broken}"


def test_make_targets_exist() -> None:
    makefile = (ROOT / "Makefile").read_text()
    targets = set(re.findall(r"^([a-zA-Z_-]+):", makefile, re.M))
    named = set(re.findall(r"\bmake ([a-z][a-z_-]+)", README.read_text()))
    assert named, "the README names no make target"
    assert named <= targets, f"README names make targets the Makefile lacks: {sorted(named - targets)}"


@pytest.mark.parametrize("page", PAGES, ids=_name)
def test_commands_exist(page: Path) -> None:
    raw = page.read_text()
    # commands are read from code only (fenced blocks and inline spans): "posediff is" in prose is not one
    code = "\n".join(FENCE.findall(raw) + CODE.findall(FENCE.sub("", raw)))
    unknown = sorted({c for c in re.findall(r"\bposediff ([a-z][a-z-]+)\b", code) if c not in COMMANDS})
    unknown_data = sorted(
        {c for c in re.findall(r"\bposediff data ([a-z][a-z-]+)\b", code) if c not in DATA_COMMANDS}
    )
    assert not unknown, f"{_name(page)} names commands posediff lacks: {unknown}"
    assert not unknown_data, f"{_name(page)} names data commands posediff lacks: {unknown_data}"


@pytest.mark.parametrize("page", PAGES, ids=_name)
def test_experiments_exist(page: Path) -> None:
    names = {n for n in re.findall(r"\+experiment=([A-Za-z0-9_]+)", page.read_text()) if not n.isupper()}
    missing = sorted(n for n in names if not (ROOT / "conf" / "experiment" / f"{n}.yaml").exists())
    assert not missing, f"{_name(page)} names experiments without a file in conf/experiment/: {missing}"


@pytest.mark.parametrize("page", PAGES, ids=_name)
def test_backticked_paths_exist(page: Path) -> None:
    missing = []
    for code in CODE.findall(page.read_text()):
        token = code.split()[0] if code.split() else ""
        token = token.split("::")[0].rstrip(",.;:")
        if not token.startswith(REPO_TOP) and token not in ("Makefile", "CHANGELOG.md", "README.md"):
            continue
        pattern = re.sub(r"<[^>]*>", "*", token)
        if "{" in pattern or token in TO_BE_WRITTEN:  # a brace list is prose, not a path
            continue
        found = any(ROOT.glob(pattern)) if "*" in pattern else (ROOT / pattern).exists()
        if not found:
            missing.append(token)
    assert not missing, f"{_name(page)} names paths that do not exist: {missing}"


def _rows(text: str) -> set[str]:
    """A table's data rows, whitespace and emphasis dropped (the header and the rule are not data)."""
    rows = set()
    for line in text.splitlines():
        cells = [c.strip(" *`") for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and len(cells) >= 3 and not set("".join(cells)) <= set("-: "):
            rows.add("|".join(cells))
    return rows


@pytest.mark.parametrize("page", DOCS, ids=_name)
def test_study_tables_live_once(page: Path) -> None:
    """A study's table lives in benchmarks/results/*.md (written by its script); docs link to it and
    do not copy its rows (the README's one results table is the exception)."""
    results = {p.name: _rows(p.read_text()) for p in (ROOT / "benchmarks" / "results").glob("*.md")}
    mine = _rows(page.read_text())
    # a header row shared with a results table is fine; data rows copied verbatim are not
    copied = {name: len(mine & rows) for name, rows in results.items() if len(mine & rows) > 1}
    assert not copied, f"{_name(page)} copies rows of {copied}; link to the results file instead"
