"""The package's code stays readable: no function or method is longer than 80 lines (its
``def`` to its last line, docstring included), as docs/development.md asks."""

from __future__ import annotations

import ast

from helpers import REPO

MAX_FUNCTION_LINES = 80


def long_functions(source: str, max_lines: int = MAX_FUNCTION_LINES) -> list[tuple[str, int]]:
    """(name, lines) of each function or method in ``source`` longer than ``max_lines``."""
    return [
        (node.name, node.end_lineno - node.lineno + 1)
        for node in ast.walk(ast.parse(source))
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and node.end_lineno - node.lineno + 1 > max_lines
    ]


def test_no_function_of_the_package_is_over_80_lines() -> None:
    found = {
        f"{path.relative_to(REPO)}:{name}": lines
        for path in sorted((REPO / "fusion_depth").rglob("*.py"))
        for name, lines in long_functions(path.read_text(encoding="utf-8"))
    }
    assert found == {}, f"functions over {MAX_FUNCTION_LINES} lines: {found}"


def test_the_check_counts_a_long_function_and_its_methods() -> None:
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    method_body = body.replace("    ", "        ")
    source = f"def long():\n{body}\n\nclass A:\n    def m(self):\n{method_body}\n"
    assert long_functions(source) == [("long", 81), ("m", 81)]
    assert long_functions("def short():\n    return 1\n") == []
