"""Render README.md's table of headline figures from ``benchmarks/results/*.json`` (written by the benchmarks
through ``results.publish``) and the choice of figures in ``benchmarks/headlines.toml``.

    python benchmarks/render_figures.py           # rewrite the table in README.md
    python benchmarks/render_figures.py --check   # exit 1 when README.md's table differs from the results
"""

from __future__ import annotations

import argparse
import json
import sys
import tomllib
from pathlib import Path

HERE = Path(__file__).resolve().parent
README = HERE.parent / "README.md"
HEADLINES = HERE / "headlines.toml"
BEGIN, END = "<!-- figures:begin -->", "<!-- figures:end -->"


def figure_value(record: dict, key: list[str]) -> float | int | str:
    """The value at ``key`` (a path of JSON keys) in a result record's ``figures``."""
    value = record["figures"]
    for part in key:
        value = value[part]
    return value


def table_row(headline: dict, record: dict) -> str:
    """One markdown row: figure, value with unit, target, date, code (``carried`` when the record was seeded from
    a run stated before the results were kept)."""
    value = figure_value(record, headline["key"])
    shown = f"{value:.{headline['digits']}f}" if isinstance(value, float | int) else str(value)
    code = f"`{record['code']}`" + (" (carried)" if "carried_from" in record else "")
    script = f"`{record['benchmark']}`"
    return (f"| {headline['figure']} ({script}) | {shown} {headline.get('unit', '')}".rstrip()
            + f" | {headline.get('target', '-')} | {record['date'][:10]} | {code} |")


def render_table(results_dir: Path = HERE / "results", headlines_file: Path = HEADLINES) -> str:
    """The markdown table of every headline in ``headlines_file``, in its order, from ``results_dir``."""
    headlines = tomllib.loads(headlines_file.read_text(encoding="utf-8"))["figure"]
    rows = ["| figure (script) | value | target | date | code |", "|---|---|---|---|---|"]
    for h in headlines:
        record = json.loads((results_dir / f"{h['result']}.json").read_text(encoding="utf-8"))
        rows.append(table_row(h, record))
    return "\n".join(rows)


def readme_table(text: str) -> str:
    """The table between the figures markers of README.md's ``text``."""
    start, end = text.index(BEGIN) + len(BEGIN), text.index(END)
    return text[start:end].strip("\n")


def with_table(text: str, table: str) -> str:
    """``text`` with the table between the figures markers replaced by ``table``."""
    start, end = text.index(BEGIN) + len(BEGIN), text.index(END)
    return text[:start] + "\n" + table + "\n" + text[end:]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only compare; exit 1 when the table differs")
    args = parser.parse_args()
    text, table = README.read_text(encoding="utf-8"), render_table()
    if readme_table(text) == table:
        return 0
    if args.check:
        print("README.md's figures table differs from benchmarks/results: run benchmarks/render_figures.py",
              file=sys.stderr)
        return 1
    README.write_text(with_table(text, table), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
