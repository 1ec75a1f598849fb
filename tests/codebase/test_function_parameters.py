"""Functions of the product's model and daemon (``daemon/``, ``pipeline/``) take at most 7 parameters, by an ast walk
(``self`` and ``cls`` not counted, ``*args`` and ``**kwargs`` counted as one each): a concept owns its
collaborators as an object instead of being handed eight of them (docs/architecture.md, "The daemon's
packages"). A function that needs more says why in its docstring, in a sentence that starts with its count
(``Eight parameters: ...``)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parents[2]  # the repository root is the package tandemscan
AREAS = ("daemon", "pipeline")
MAX_PARAMETERS = 7
NUMBERS = ("zero one two three four five six seven eight nine ten eleven twelve thirteen fourteen fifteen sixteen "
           "seventeen eighteen nineteen twenty").split()


def parameter_count(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """A function's parameters: positional-only, positional, keyword-only, ``*args`` and ``**kwargs``, less a
    leading ``self`` or ``cls``."""
    a = node.args
    names = [p.arg for p in (*a.posonlyargs, *a.args, *a.kwonlyargs, *filter(None, (a.vararg, a.kwarg)))]
    return len(names) - (1 if names[:1] in (["self"], ["cls"]) else 0)


def says_why(docstring: str, count: int) -> bool:
    """Whether ``docstring`` has a sentence that starts with the function's own count: ``Nine parameters:``."""
    words = {str(count)} | ({NUMBERS[count]} if count < len(NUMBERS) else set())
    return any(re.search(rf"\b{w} parameters:", docstring, re.IGNORECASE) for w in words)


def unexplained_long_signatures(root: Path) -> list[str]:
    """``"path:line name (N parameters)"`` for every function of :data:`AREAS` over :data:`MAX_PARAMETERS` whose
    docstring does not say why with its own count."""
    found = []
    for area in AREAS:
        for path in sorted((root / area).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) \
                        and (n := parameter_count(node)) > MAX_PARAMETERS \
                        and not says_why(ast.get_docstring(node) or "", n):
                    found.append(f"{path.relative_to(root).as_posix()}:{node.lineno} {node.name} ({n} parameters)")
    return found


def test_no_product_function_takes_more_than_seven_parameters_without_saying_why():
    assert unexplained_long_signatures(PACKAGE_ROOT) == []


def test_a_planted_long_signature_is_found(tmp_path):
    for area in AREAS:
        (tmp_path / area).mkdir()
    (tmp_path / "daemon" / "planted.py").write_text(
        "def eight(a, b, c, d, e, f, g, h):\n    pass\n\n\n"
        "class Runner:\n    def __init__(self, a, b, c, d, e, f, g):\n        pass\n\n"
        "    async def step(self, a, b, c, d, e, f, g, /, *, h=1):\n        pass\n\n"
        "    def spread(self, a, b, c, d, e, f, *rest, **options):\n        pass\n")
    (tmp_path / "pipeline" / "explained.py").write_text(
        'def solve(a, b, c, d, e, f, g, h):\n    """Solve it.\n\n    Eight parameters: the solver\'s own inputs.\n'
        '    """\n\n\ndef miscounted(a, b, c, d, e, f, g, h, i):\n    """8 parameters: stale."""\n\n\n'
        'def counted(a, b, c, d, e, f, g, h, i):\n    """Solve it. 9 parameters: each one needed."""\n')
    assert unexplained_long_signatures(tmp_path) == [
        "daemon/planted.py:1 eight (8 parameters)",
        "daemon/planted.py:9 step (8 parameters)",
        "daemon/planted.py:12 spread (8 parameters)",
        "pipeline/explained.py:8 miscounted (9 parameters)",
    ]
