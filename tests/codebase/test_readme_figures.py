"""README.md's table of headline figures is the benchmarks' results (``benchmarks/results/*.json``), rendered by
``benchmarks/render_figures.py``; a benchmark keeps its figures there through ``benchmarks/results.py``."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BENCHMARKS = ROOT / "benchmarks"


def _module(name: str):
    spec = importlib.util.spec_from_file_location(f"benchmarks_{name}", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


render = _module("render_figures")
results = _module("results")


def test_readme_table_is_the_results():
    """The table between README's figures markers is what the results files render to, row for row."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert render.readme_table(readme) == render.render_table()


def test_a_published_figure_changes_the_table(tmp_path, capsys):
    """A benchmark's ``publish`` keeps its figures with date and code and prints them as the last line; the
    rendered table then shows the new value, so README's table no longer matches until it is re-rendered."""
    shutil.copytree(BENCHMARKS / "results", tmp_path / "results")
    old = json.loads((tmp_path / "results" / "gc_pause.json").read_text())
    figures = old["figures"] | {"full_collection_ms_frozen": 3.5}
    path = results.publish("gc_pause", figures, results_dir=tmp_path / "results")
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == figures
    record = json.loads(path.read_text())
    assert record["figures"] == figures and "carried_from" not in record
    assert record["code"] != "unknown" and record["date"][:2] == "20"
    table = render.render_table(tmp_path / "results")
    row = next(line for line in table.splitlines() if "`gc_pause`" in line)
    assert "| 3.5 ms |" in row and "(carried)" not in row
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert render.readme_table(readme) != table
    assert render.readme_table(render.with_table(readme, table)) == table


def test_every_headline_names_a_figure_that_exists():
    """A headline whose key is missing from its results file fails the rendering, not silently."""
    for line in render.render_table().splitlines()[2:]:
        assert line.count("|") == 6
    with pytest.raises(KeyError):
        render.figure_value({"figures": {"a": {"b": 1}}}, ["a", "c"])
