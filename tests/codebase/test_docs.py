"""The documentation stays usable (docs/README.md): pages short enough to read, and every page a docstring,
a test, a benchmark or another page cites exists."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CITED = re.compile(r"docs/([\w./-]+\.md)")


def test_readme_and_every_docs_page_are_short():
    assert (ROOT / "README.md").stat().st_size < 12_000
    long = {p.relative_to(ROOT).as_posix(): p.stat().st_size for p in (ROOT / "docs").rglob("*.md")
            if p.stat().st_size > 20_000}
    assert not long, f"docs pages over 20 KB (split them by concept): {long}"


def test_every_cited_docs_page_exists():
    sources = [ROOT / "README.md", ROOT / "CHANGELOG.md", *(ROOT / "docs").rglob("*.md")]
    for folder in ("daemon", "pipeline", "drivers", "config", "sim_drivers", "benchmarks", "tests"):
        sources += (ROOT / folder).rglob("*.py")
    missing = {f"{src.relative_to(ROOT)}: docs/{page}" for src in sources
               for page in CITED.findall(src.read_text(encoding="utf-8"))
               if not (ROOT / "docs" / page.rstrip(".")).exists()}
    assert not missing, sorted(missing)
