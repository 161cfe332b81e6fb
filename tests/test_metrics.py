"""The package's complexity figures (radon, pinned in the ``dev`` extra), and a ratchet on them.

``make metrics`` (``python tests/test_metrics.py``) prints radon's mean cyclomatic complexity
over every block (class, function, method) of the package, the blocks at grade E/F
(complexity > 30) and the classes over 300 lines — the figures of docs/architecture.md's table.

The test fails when a block reaches grade E/F that is not in :data:`ALLOWED`, the blocks that
were there when the ratchet was set; the list may only shrink: a block brought under grade E
leaves it, and the test says so.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_class_size import LIMIT, PACKAGES, ROOT, class_spans  # noqa: E402

GRADE_E = 31  # radon's grade E starts here (A 1–5, B 6–10, C 11–20, D 21–30, E 31–40, F 41+)

# E/F blocks still in the package ("path qualified.name"), to be split along their decisions;
# nothing may join this list, and an entry whose block drops below grade E must leave it.
ALLOWED = frozenset({
    "daq/bus/assembler.py SampleLayout.__init__",
    "daq/bus/assembler.py SampleLayout.sample",
    "daq/bus/decoder.py DecodeTable.__init__",
    "daq/web/dictionary.py points",
})


@dataclass
class Metrics:
    blocks: int
    mean: float  # radon's "Average complexity" over the same blocks (radon cc -a)
    grade_ef: dict[str, int]  # "path qualified.name" -> complexity, complexity ≥ GRADE_E
    large_classes: dict[str, int]  # "path Class" -> lines, over test_class_size.LIMIT


def measure(root: Path = ROOT, packages: tuple[str, ...] = PACKAGES) -> Metrics:
    """The figures of every ``*.py`` under ``packages`` (radon's own block list: functions,
    classes and their methods; closures counted in their function, as ``radon cc`` does)."""
    from radon.complexity import cc_visit, sorted_results

    total = count = 0
    grade_ef: dict[str, int] = {}
    large: dict[str, int] = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            rel = path.relative_to(root).as_posix()
            source = path.read_text()
            for block in sorted_results(cc_visit(source)):
                total += block.complexity
                count += 1
                if block.complexity >= GRADE_E:
                    grade_ef[f"{rel} {block.fullname}"] = block.complexity
            for name, _, lines, _ in class_spans(source):
                if lines > LIMIT:
                    large[f"{rel} {name}"] = lines
    return Metrics(count, total / max(count, 1), grade_ef, large)


def report(m: Metrics) -> str:
    lines = [f"radon mean cyclomatic complexity: {m.mean:.2f} over {m.blocks} blocks "
             f"({', '.join(PACKAGES)})",
             f"blocks at grade E/F (complexity ≥ {GRADE_E}): {len(m.grade_ef)}"]
    lines += [f"  {c:4d}  {k}" for k, c in sorted(m.grade_ef.items(), key=lambda kv: -kv[1])]
    lines.append(f"classes over {LIMIT} lines: {len(m.large_classes)}")
    lines += [f"  {n:4d}  {k}" for k, n in sorted(m.large_classes.items(), key=lambda kv: -kv[1])]
    return "\n".join(lines)


def _radon() -> None:
    pytest.importorskip("radon", reason="radon is missing: pip install '.[dev]' (make lint "
                        "installs it) to measure the complexity")


def test_no_new_block_at_grade_e_or_f():
    _radon()
    found = measure().grade_ef
    new = {k: v for k, v in found.items() if k not in ALLOWED}
    assert new == {}, (
        f"blocks at radon grade E/F (complexity ≥ {GRADE_E}) not in the allow-list: split "
        "them along their decisions (a table, a class per variant, helpers) — the list may "
        "not grow")
    assert sorted(ALLOWED - set(found)) == [], (
        "blocks below grade E now (or renamed): remove them from ALLOWED in "
        "tests/test_metrics.py (the list may only shrink)")


def test_the_measure_sees_a_complex_block():
    # the measure itself, on a made-up package: one function of 31 branches is grade E, a
    # class of 301 lines is over the limit
    _radon()
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        pkg = Path(d) / "pkg"
        pkg.mkdir()
        branches = "\n".join(f"    if x == {i}:\n        return {i}" for i in range(GRADE_E - 1))
        body = "\n".join(f"    a{i} = {i}" for i in range(LIMIT))
        (pkg / "m.py").write_text(f"def f(x):\n{branches}\n    return -1\n\n\n"
                                  f"def g(x):\n    return x\n\n\nclass Big:\n{body}\n")
        m = measure(Path(d), ("pkg",))
    assert m.grade_ef == {"pkg/m.py f": GRADE_E}
    assert m.large_classes == {"pkg/m.py Big": LIMIT + 1}
    assert m.blocks == 3 and m.mean == pytest.approx((GRADE_E + 1 + 1) / 3)


if __name__ == "__main__":  # make metrics
    try:
        import radon  # noqa: F401
    except ImportError:
        sys.exit("make metrics: radon is missing — run `make lint` once (it installs the dev "
                 "extra) or pip install '.[dev]'")
    print(report(measure()))
