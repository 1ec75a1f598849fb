"""The documentation stays usable (docs/README.md): pages short enough to read."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_readme_and_every_docs_page_are_short():
    assert (ROOT / "README.md").stat().st_size < 12_000
    long = {p.relative_to(ROOT).as_posix(): p.stat().st_size for p in (ROOT / "docs").rglob("*.md")
            if p.stat().st_size > 20_000}
    assert not long, f"docs pages over 20 KB (split them by concept): {long}"

