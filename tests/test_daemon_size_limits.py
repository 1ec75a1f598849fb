"""Size limits of ``daemon/`` (issue 20): no module over 350 lines, no function over 80 lines, by an ast walk."""

from __future__ import annotations

import ast
from pathlib import Path

DAEMON = Path(__file__).resolve().parents[1] / "daemon"
MAX_MODULE_LINES = 350
MAX_FUNCTION_LINES = 80


def _over_limits() -> set[str]:
    over = set()
    for path in sorted(DAEMON.rglob("*.py")):
        name = path.relative_to(DAEMON).as_posix()
        text = path.read_text(encoding="utf-8")
        if text.count("\n") > MAX_MODULE_LINES:
            over.add(name)
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) \
                    and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES:
                over.add(f"{name}:{node.name}")
    return over


def test_daemon_modules_and_functions_stay_within_their_size_limits():
    assert _over_limits() == set()
