"""Shared fixtures (the default config, the QIF schema, a count of raw scan reads), a guard that no test leaves
asyncio tasks running, and the markers each folder's tests carry (docs/testing.md)."""

from __future__ import annotations

import asyncio
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from tandemscan.config import CellConfig, load_config

TESTS = Path(__file__).resolve().parent
MARKED_FOLDERS = ("hil", "browser", "e2e")  # a test under tests/<folder>/ carries that marker (pyproject.toml)


def pytest_collection_modifyitems(config, items):
    """Mark each test by its folder, so that ``-m "not hil and not browser"`` selects the inner loop."""
    for item in items:
        path = Path(item.path).resolve()
        if path.is_relative_to(TESTS) and path.relative_to(TESTS).parts[0] in MARKED_FOLDERS:
            item.add_marker(path.relative_to(TESTS).parts[0])


@pytest.fixture
def sim_config() -> CellConfig:
    """The shipped simulated-cell configuration, on its nominal mounts: a current calibration a developer's
    `tandemscan calibrate` left in out/ does not reach the tests."""
    config = load_config()
    return config.model_copy(update={"job": config.job.model_copy(update={"installation_source": "nominal"})})


@pytest.fixture
def scan_reads(monkeypatch) -> Counter[str]:
    """The reads of raw scan files in this process from now on: each ``np.load`` of a file in a ``scans/`` folder,
    counted by file name (docs/end-of-job.md: a raw scan is read at most twice after it is written)."""
    reads: Counter[str] = Counter()
    load = np.load

    def counting_load(file, *args, **kwargs):
        if Path(file).parent.name == "scans":
            reads[Path(file).name] += 1
        return load(file, *args, **kwargs)

    monkeypatch.setattr(np, "load", counting_load)
    return reads


@pytest.fixture(autouse=True)
async def _no_leftover_tasks():
    """Fail a test that leaves asyncio tasks behind (a leaked reader or heartbeat)."""
    yield
    current = asyncio.current_task()
    left = [t for t in asyncio.all_tasks() if t is not current and not t.done()]
    for t in left:
        t.cancel()
    assert not left, f"test left asyncio tasks running: {left}"


QIF_SCHEMA = "../shared/qif/schema/QIFDocument.xsd"  # the QIF 3.0 schema, beside the project (../shared/qif)


@pytest.fixture(scope="session")
def qif_schema(tmp_path_factory):
    """The QIF 3.0 schema, loaded once per session (10-30 s). QIFDocument.xsd imports the XML-signature
    namespace, which no QIF type uses; the shared copy of that schema is moved into the QIF namespace (for
    Microsoft's tools) and so cannot stand for it: an empty schema of the namespace does."""
    import xmlschema

    schema = TESTS.parent / QIF_SCHEMA
    dsig = tmp_path_factory.mktemp("qif") / "xmldsig-namespace.xsd"
    dsig.write_text('<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema" '
                    'targetNamespace="http://www.w3.org/2000/09/xmldsig#"/>\n')
    return xmlschema.XMLSchema(str(schema), locations=[("http://www.w3.org/2000/09/xmldsig#", str(dsig))])
