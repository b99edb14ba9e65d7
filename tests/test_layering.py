"""Layering (STYLE §8, §13): no engine or technique imports a reader, the evaluation, the report or the CLI.

Data flows one way, ``io -> engines (techniques, kalman, geo) -> eval -> report``, with the CLI
on top. The check parses every module under ``iotnav/engines`` and ``iotnav/techniques`` with
:mod:`ast` (imports inside functions included, relative imports resolved) and lists each
import of ``iotnav.io``, ``iotnav.eval``, ``iotnav.report`` or ``iotnav.cli``. The in-memory
timeline that engines consume is allowed: :mod:`iotnav.io.log` (the merged ``Log``) and
:mod:`iotnav.io.schema` (its column names), the one place data crosses from ``io`` into the
engines; no reader or writer.

File size (issue 21, "no file over about 800 lines"): no source file under ``src/iotnav`` has more
than :data:`LINE_LIMIT` lines, except the files named in :data:`OVER_LIMIT`, the files over the
limit on 2026-12-02 that other work owns. The list can only shrink: a listed file that comes
under the limit fails the test until it is removed from the list, and a file not listed that
grows over the limit fails it too.
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "iotnav"
#: Packages whose modules are checked.
INNER = ("engines", "techniques")
#: Layers the inner packages must not import.
FORBIDDEN = ("iotnav.io", "iotnav.eval", "iotnav.report", "iotnav.cli")
#: The timeline data model of ``io`` (types, not readers): allowed.
ALLOWED = ("iotnav.io.log", "iotnav.io.schema")

#: Most lines a source file under ``src/iotnav`` may have (issue 21: "about 800").
LINE_LIMIT = 800
#: Files over :data:`LINE_LIMIT` today (2026-12-02, paths relative to ``src/iotnav``), each to
#: be split by the work that owns it; remove a file here when it comes under the limit.
OVER_LIMIT: frozenset[str] = frozenset()


def _within(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def imported_names(path: Path, package: str) -> list[tuple[int, str]]:
    """``(line, module)`` of every import in a file (``from a import b`` gives ``a`` and ``a.b``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolved against the file's package
                parts = package.split(".")
                parts = parts[: len(parts) - node.level + 1]
                base = ".".join([*parts, base] if base else parts)
            out.append((node.lineno, base))
            out += [(node.lineno, f"{base}.{a.name}") for a in node.names]
    return out


def violations(src: Path = SRC) -> list[str]:
    """``file:line imports module`` for each forbidden import under the inner packages of ``src``."""
    found = []
    for inner in INNER:
        for path in sorted((src / inner).rglob("*.py")):
            rel = path.relative_to(src.parent)
            package = ".".join(rel.parent.parts)
            for line, name in imported_names(path, package):
                if _within(name, FORBIDDEN) and not _within(name, ALLOWED):
                    found.append(f"{rel}:{line} imports {name}")
    return sorted(set(found))


def test_engines_and_techniques_import_no_outer_layer() -> None:
    assert SRC.is_dir(), SRC
    assert violations() == []


def test_the_check_finds_forbidden_imports(tmp_path: Path) -> None:
    """A planted tree: top-level, lazy, relative and ``from iotnav import ...`` imports are all found."""
    root = tmp_path / "iotnav"
    (root / "engines" / "sub").mkdir(parents=True)
    (root / "techniques").mkdir()
    (root / "engines" / "a.py").write_text(
        "from iotnav.eval.consistency import InnovationLog\nfrom iotnav.io.log import Log\n"
    )
    (root / "engines" / "sub" / "b.py").write_text("def f():\n    from ...report import html\n")
    (root / "techniques" / "c.py").write_text("from iotnav import cli\nimport iotnav.io.nmea\n")
    found = violations(root)
    assert found == [
        "iotnav/engines/a.py:1 imports iotnav.eval.consistency",
        "iotnav/engines/a.py:1 imports iotnav.eval.consistency.InnovationLog",
        "iotnav/engines/sub/b.py:2 imports iotnav.report",
        "iotnav/engines/sub/b.py:2 imports iotnav.report.html",
        "iotnav/techniques/c.py:1 imports iotnav.cli",
        "iotnav/techniques/c.py:2 imports iotnav.io.nmea",
    ]


def line_counts(src: Path = SRC) -> dict[str, int]:
    """Lines of every ``.py`` file under ``src``, by path relative to it (``/`` separated)."""
    return {
        path.relative_to(src).as_posix(): len(path.read_text(encoding="utf-8").splitlines())
        for path in sorted(src.rglob("*.py"))
    }


def size_violations(
    counts: dict[str, int], limit: int = LINE_LIMIT, allowed: frozenset[str] = OVER_LIMIT
) -> list[str]:
    """Files over ``limit`` that are not ``allowed``, and ``allowed`` files no longer over it."""
    over = [f"{name}: {n} lines > {limit}" for name, n in counts.items() if n > limit and name not in allowed]
    stale = [
        f"{name}: listed in OVER_LIMIT but {counts.get(name, 0)} lines (remove it from the list)"
        for name in sorted(allowed)
        if counts.get(name, 0) <= limit
    ]
    return over + stale


def test_no_source_file_over_the_line_limit() -> None:
    counts = line_counts()
    assert len(counts) > 100, SRC  # the whole package was scanned
    assert size_violations(counts) == []


def test_the_size_check_finds_new_and_stale_entries() -> None:
    counts = {"a.py": 801, "b.py": 800, "c.py": 900, "d.py": 10}
    assert size_violations(counts, 800, frozenset({"c.py", "d.py", "gone.py"})) == [
        "a.py: 801 lines > 800",
        "d.py: listed in OVER_LIMIT but 10 lines (remove it from the list)",
        "gone.py: listed in OVER_LIMIT but 0 lines (remove it from the list)",
    ]
