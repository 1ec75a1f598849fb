"""Function size in ``daemon/``: no function over 80 lines, by an ast walk (one function, one job).

Modules are split by concept, not to fit a line count (issue 45): there is no module cap.
"""

from __future__ import annotations

import ast
from pathlib import Path

DAEMON = Path(__file__).resolve().parents[2] / "daemon"
MAX_FUNCTION_LINES = 80


def _functions_over_limit() -> set[str]:
    over = set()
    for path in sorted(DAEMON.rglob("*.py")):
        name = path.relative_to(DAEMON).as_posix()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) \
                    and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES:
                over.add(f"{name}:{node.name}")
    return over


def test_daemon_functions_stay_within_their_size_limit():
    assert _functions_over_limit() == set()
