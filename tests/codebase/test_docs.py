"""The documentation stays usable (docs/README.md): pages short enough to read, every page (and section) a
docstring, a test, a benchmark or another page cites exists, and every repository file a page names exists."""

from __future__ import annotations

import argparse
import fnmatch
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CITED = re.compile(r"docs/([\w./-]+\.md)")
# a repository path a page names in backticks: `pipeline/compute.py`, `tests/drivers/test_drivers_*.py`,
# `benchmarks/results/`; a path with an upper-case placeholder (`benchmarks/NAME.py`) is a pattern, not a file
NAMED_PATH = re.compile(r"`((?:daemon|drivers|sim_drivers|pipeline|config|tests|benchmarks|docs|systemd)/[\w./*-]*)")
PLACEHOLDER = re.compile(r"\b[A-Z]{2,}\b")
# a cited section: the docs path of a page, then its heading in double quotes (which may run over lines and
# comment marks)
CITED_SECTION = re.compile(r'docs/([\w./-]+\.md),?\s+"([^"]+)"')
# a configuration key in backticks: `[job] voxel_mm`, `[sim.as_built] deviations`, `[calibration] centre_*_mm`
NAMED_KEY = re.compile(r"`\[([a-z_.]+)\] ([a-z_0-9*]+)")
# a command line: `tandemscan job submit --serial S` (sub-commands, then the rest of the line or code span)
NAMED_COMMAND = re.compile(r"tandemscan ([a-z][a-z-]*(?: [a-z][a-z|-]*)?)([^`\n]*)")
COMMAND_OPTION = re.compile(r"(?<![\w-])(--[a-z][a-z0-9-]*)")


def test_readme_and_every_docs_page_are_short():
    assert (ROOT / "README.md").stat().st_size < 12_000
    long = {p.relative_to(ROOT).as_posix(): p.stat().st_size for p in (ROOT / "docs").rglob("*.md")
            if p.stat().st_size > 20_000}
    assert not long, f"docs pages over 20 KB (split them by concept): {long}"


def _citing_files() -> list[Path]:
    sources = [ROOT / "README.md", ROOT / "CHANGELOG.md", *(ROOT / "docs").rglob("*.md")]
    for folder in ("daemon", "pipeline", "drivers", "config", "sim_drivers", "benchmarks", "tests"):
        sources += (ROOT / folder).rglob("*.py")
    return sources


def test_every_cited_docs_page_exists():
    missing = {f"{src.relative_to(ROOT)}: docs/{page}" for src in _citing_files()
               for page in CITED.findall(src.read_text(encoding="utf-8"))
               if not (ROOT / "docs" / page.rstrip(".")).exists()}
    assert not missing, sorted(missing)


def test_every_cited_docs_section_exists():
    """A section is cited by (part of) its heading, or by the bold words that open its paragraph."""
    missing = set()
    for src in _citing_files():
        for page, section in CITED_SECTION.findall(src.read_text(encoding="utf-8")):
            path = ROOT / "docs" / page
            if not path.exists():
                continue  # test_every_cited_docs_page_exists names it
            title = re.sub(r"[\s#]+", " ", section).strip(" .").lower()
            text = path.read_text(encoding="utf-8")
            headings = [line.lstrip("#").strip().lower() for line in text.splitlines() if line.startswith("#")]
            if not any(title in h for h in headings) and f"**{title}" not in text.lower():
                missing.add(f"{src.relative_to(ROOT)}: docs/{page}, \"{section}\"")
    assert not missing, sorted(missing)


def test_every_repository_file_a_page_names_exists():
    pages = [ROOT / "README.md", *(ROOT / "docs").rglob("*.md")]
    missing = {f"{page.relative_to(ROOT)}: {path}" for page in pages
               for path in NAMED_PATH.findall(page.read_text(encoding="utf-8"))
               if not PLACEHOLDER.search(path) and not _exists(path.rstrip("."))}
    assert not missing, f"docs name files that are not in the repository (moved or renamed?): {sorted(missing)}"


def _exists(path: str) -> bool:
    """Whether a repository path, or a glob such as ``tests/drivers/test_*.py``, names at least one file."""
    return any(ROOT.glob(path)) if "*" in path else (ROOT / path).exists()


def test_every_config_key_a_page_names_exists():
    """`[section] key` in a page (`key_*` a family of keys) is a field of that section's model: the product's
    (`config/models.py`, a sub-table by its own name, `[can]`) or the simulator's (`[sim]`, `[hil]`)."""
    from tandemscan.config.device_registry import simulator_settings_model
    from tandemscan.config.models import CellConfig

    keys = _section_fields(CellConfig, "")
    for section in ("sim", "hil"):
        keys.update(_section_fields(simulator_settings_model(section), section))
    missing = set()
    for page in [ROOT / "README.md", *(ROOT / "docs").rglob("*.md")]:
        for section, key in NAMED_KEY.findall(page.read_text(encoding="utf-8")):
            fields = keys.get(section, set())
            if not fnmatch.filter(fields, key):
                missing.add(f"{page.relative_to(ROOT)}: [{section}] {key}")
    assert not missing, f"docs name config keys no model has (renamed or moved?): {sorted(missing)}"


def _section_fields(model: type, name: str) -> dict[str, set[str]]:
    """Field names by table name (``a.b`` and ``b`` alike) for ``model`` and every model nested in it."""
    from pydantic import BaseModel

    found: dict[str, set[str]] = {}
    if name:
        for table in {name, name.rsplit(".", 1)[-1]}:
            found.setdefault(table, set()).update(model.model_fields)
    for field, info in model.model_fields.items():
        for inner in (info.annotation, *getattr(info.annotation, "__args__", ())):
            if isinstance(inner, type) and issubclass(inner, BaseModel) and inner is not BaseModel:
                for table, fields in _section_fields(inner, f"{name}.{field}".lstrip(".")).items():
                    found.setdefault(table, set()).update(fields)
    return found


def test_every_code_block_closes():
    """An unclosed fence turns the rest of a page into code."""
    open_fences = [p.relative_to(ROOT).as_posix() for p in [ROOT / "README.md", *(ROOT / "docs").rglob("*.md")]
                   if sum(line.lstrip().startswith("```") for line in p.read_text(encoding="utf-8").splitlines()) % 2]
    assert not open_fences, open_fences


def test_every_command_option_a_page_names_exists():
    """`tandemscan job submit --serial S` in a page: `job submit` is a command and `--serial` one of its options."""
    from tandemscan.daemon.cli import build_parser

    missing = set()
    for page in [ROOT / "README.md", *(ROOT / "docs").rglob("*.md")]:
        for words, rest in NAMED_COMMAND.findall(page.read_text(encoding="utf-8")):
            parser, command = build_parser(), ["tandemscan"]
            for word in words.split():
                commands = _commands(parser)
                if word.split("|")[0] not in commands:
                    break
                parser = commands[word.split("|")[0]]
                command.append(word)
            options = {o for action in parser._actions for o in action.option_strings}
            missing.update(f"{page.relative_to(ROOT)}: {' '.join(command)} {flag}"
                           for flag in COMMAND_OPTION.findall(rest) if flag not in options)
    assert not missing, sorted(missing)


def _commands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The sub-commands of ``parser`` by name (none for a leaf)."""
    return next((dict(a.choices) for a in parser._actions if isinstance(a, argparse._SubParsersAction)), {})
