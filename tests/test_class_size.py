"""Classes with one job: no class of the package holds more than 300 lines (no exemption: a
longer class is split along its jobs, as the identification's skeleton and its per-mode
classes were).

The span of a class is counted from its ``class`` line (decorators included) to its last
line, as ``ast`` reports it, comments and docstrings included: what a reader has to scroll
through.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("daq", "estimator", "sim_bus", "config", "rsra")
LIMIT = 300


def class_spans(source: str) -> list[tuple[str, int, int, str]]:
    """(qualified name, first line, line count, docstring) of every class in a module's source."""
    spans = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef):
                first = min([child.lineno] + [d.lineno for d in child.decorator_list])
                count = child.end_lineno - first + 1
                name = prefix + child.name
                spans.append((name, first, count, ast.get_docstring(child) or ""))
                visit(child, name + ".")
            elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                visit(child, prefix + child.name + ".<locals>.")

    visit(ast.parse(source), "")
    return spans


def oversized(limit: int = LIMIT) -> dict[str, str]:
    """'path Class' -> 'path:line Class: N lines' for every class over ``limit`` lines."""
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for name, first, count, _ in class_spans(path.read_text()):
                if count > limit:
                    rel = path.relative_to(ROOT)
                    found[f"{rel} {name}"] = f"{rel}:{first} {name}: {count} lines"
    return found


def test_no_class_over_the_limit():
    assert list(oversized().values()) == [], (
        f"classes over {LIMIT} lines: split them along their responsibilities (a skeleton and "
        "a class per variant, a registry, helpers of their own)")


def test_the_measure_sees_a_long_class():
    # the measure itself, on made-up sources: a long class is seen, nested ones too
    body = "\n".join(f"    x{i} = {i}" for i in range(LIMIT + 5))
    long_class = f"class Big:\n    '''A big one.'''\n{body}\n"
    spans = class_spans(long_class)
    assert spans[0][0] == "Big" and spans[0][2] == LIMIT + 7
    nested = "def f():\n    class Inner:\n        pass\nclass Outer:\n    class In:\n        pass\n"
    assert [s[0] for s in class_spans(nested)] == ["f.<locals>.Inner", "Outer", "Outer.In"]


@pytest.mark.parametrize("limit", [LIMIT])
def test_sizes_report(limit, capsys):
    # not an assertion: prints the largest classes (pytest -s shows them) for the record
    spans = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for name, first, count, _ in class_spans(path.read_text()):
                spans.append((count, f"{path.relative_to(ROOT)}:{first} {name}"))
    for count, where in sorted(spans, reverse=True)[:12]:
        print(f"{count:5d}  {where}")
    assert spans
