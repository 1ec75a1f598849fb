"""Shared fixtures: the default config, and a guard that no test leaves asyncio tasks running."""

from __future__ import annotations

import asyncio

import pytest
from tandemscan.config import CellConfig, load_config


@pytest.fixture
def sim_config() -> CellConfig:
    """The shipped simulated-cell configuration."""
    return load_config()


@pytest.fixture(autouse=True)
async def _no_leftover_tasks():
    """Fail a test that leaves asyncio tasks behind (a leaked reader or heartbeat)."""
    yield
    current = asyncio.current_task()
    left = [t for t in asyncio.all_tasks() if t is not current and not t.done()]
    for t in left:
        t.cancel()
    assert not left, f"test left asyncio tasks running: {left}"
