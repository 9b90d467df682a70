"""The project's import graph: no circle among its modules (imports inside functions included: a
circle hidden in a function is still one), and no project import inside a function without a stated
reason (a comment on its line, or a comment line just above its block of imports: a heavy optional
dependency, a cycle that cannot be cut)."""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("emulator", "policies", "hil")


def modules() -> dict[str, Path]:
    """Every module of the project: dotted name -> file."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = path
    return out


def _type_checking_only(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def imports(tree: ast.Module) -> Iterator[tuple[ast.Import | ast.ImportFrom, bool]]:
    """Each import statement that runs (those under ``if TYPE_CHECKING`` do not), and whether it is
    inside a function."""

    def walk(node: ast.AST, in_function: bool) -> Iterator[tuple[ast.Import | ast.ImportFrom, bool]]:
        for child in ast.iter_child_nodes(node):
            if _type_checking_only(child):
                continue
            if isinstance(child, ast.Import | ast.ImportFrom):
                yield child, in_function
            yield from walk(child, in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef))

    yield from walk(tree, False)


def targets(node: ast.Import | ast.ImportFrom, here: str, known: dict[str, Path]) -> set[str]:
    """The project modules an import statement loads (the most specific one each name names)."""
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    else:
        base = node.module or ""
        if node.level:
            package = here.split(".")[: len(here.split(".")) - node.level + (here in _packages(known))]
            base = ".".join([*package, *([base] if base else [])])
        names = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
    return {n for n in names if n in known}


def _packages(known: dict[str, Path]) -> set[str]:
    return {name for name, path in known.items() if path.name == "__init__.py"}


def graph() -> dict[str, set[str]]:
    known = modules()
    return {name: {t for node, _ in imports(ast.parse(path.read_text())) for t in targets(node, name, known)}
            for name, path in known.items()}


def circles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


_DIRECTIVES = re.compile(r"noqa(:\s*[A-Z0-9, ]+)?|type:\s*ignore(\[[^\]]*\])?")


def says_why(line: str) -> bool:
    """Whether ``line`` has a comment that gives a reason: words, not only a linter's directive."""
    _, hash_, comment = line.partition("#")
    return bool(hash_) and re.search(r"[A-Za-z]", _DIRECTIVES.sub("", comment)) is not None


def unexplained_inner_imports() -> list[str]:
    """Project imports inside functions with no comment on their line nor on the line above their
    block of imports."""
    known = modules()
    out = []
    for name, path in known.items():
        lines = path.read_text().splitlines()
        for node, in_function in imports(ast.parse("\n".join(lines))):
            if not in_function or not targets(node, name, known):
                continue
            i = node.lineno - 1
            if says_why(lines[node.end_lineno - 1]) or says_why(lines[i]):
                continue
            above = i - 1
            while above >= 0 and lines[above].strip().startswith(("from ", "import ")):
                above -= 1
            if above >= 0 and lines[above].strip().startswith("#") and says_why(lines[above]):
                continue
            out.append(f"{path.relative_to(ROOT)}:{node.lineno}: {lines[i].strip()}")
    return out


def test_the_graph_sees_the_projects_imports() -> None:
    edges = graph()
    assert "hil.scenario.schema" in edges["hil.scenario.loader"]
    assert "hil.runner.emulator_side" in edges["hil.runner.run"]
    assert "policies.onboard.cli" in edges["hil.commands.onboard"]  # (inside a function)
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_a_linters_directive_is_no_reason() -> None:
    assert says_why("    from a import b  # (heavy: numba, only when a file needs it)")
    assert not says_why("    from a import b  # noqa: F401")
    assert not says_why("    from a import b  # type: ignore[attr-defined]")
    assert not says_why("    from a import b")


def test_no_import_circle_among_the_projects_modules() -> None:
    assert circles(graph()) == []


def test_every_project_import_inside_a_function_says_why() -> None:
    assert unexplained_inner_imports() == []
