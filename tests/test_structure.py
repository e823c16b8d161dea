"""The shape of the code (docs/design.md section 2): modules of at most ~400 lines, functions of
at most ~60 (docstrings aside), no import circle between the project's modules, every import at
the top of its module unless it says why it is lazy (`# lazy: ...` on the line or the one
above), and nothing outside `benchmarks/` referring to the shared folder beside the repository
(a clone has none)."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("core", "worker", "service", "native")
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 60
# Generated Alembic migrations are data in code form.
EXEMPT = ("worker/migrations/versions/",)


def _sources() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")
                  if not str(p.relative_to(ROOT)).startswith(EXEMPT))


def _rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _functions(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node


def _body_lines(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    first = fn.body[0]
    docstring = isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) \
        and isinstance(first.value.value, str)
    start = first.end_lineno + 1 if docstring and len(fn.body) > 1 else fn.lineno
    return fn.end_lineno - start + 1


def test_modules_are_at_most_400_lines():
    long = {_rel(p): n for p in _sources() if (n := len(p.read_text().splitlines()))
            > MAX_MODULE_LINES}
    assert not long, f"split these modules: {long}"


def test_functions_are_at_most_60_lines():
    long = {}
    for path in _sources():
        for fn in _functions(ast.parse(path.read_text())):
            if (n := _body_lines(fn)) > MAX_FUNCTION_LINES:
                long[f"{_rel(path)}:{fn.lineno} {fn.name}"] = n
    assert not long, f"split these functions: {long}"


def _imports(path: Path, modules: set[str]) -> list[str]:
    """The project modules `path` imports when it runs (at its top or inside its functions;
    `if TYPE_CHECKING:` blocks never run)."""
    tree = ast.parse(path.read_text())
    typing_only = {id(n) for top in tree.body if isinstance(top, ast.If)
                   and "TYPE_CHECKING" in ast.unparse(top.test) for n in ast.walk(top)}
    out = []
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules
                     else node.module for a in node.names]
        for name in names:
            while name and name not in modules:
                name = name.rpartition(".")[0]
            if name:
                out.append(name)
    return out


def _graph() -> dict[str, set[str]]:
    paths = {_module_name(p): p for p in _sources()}
    return {name: {m for m in _imports(path, set(paths)) if m != name}
            for name, path in paths.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_circles():
    assert not _cycles(_graph()), "these modules import each other (directly or lazily)"


def test_the_cycle_finder_sees_a_circle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_imports_are_at_the_top_or_say_why_not():
    modules = {_module_name(p) for p in _sources()}
    hidden = []
    for path in _sources():
        lines = path.read_text().splitlines()
        tree = ast.parse("\n".join(lines))
        for node in ast.walk(tree):
            if not isinstance(node, (ast.Import, ast.ImportFrom)):
                continue
            if any(node is n for n in tree.body) or _in_top_block(tree, node):
                continue
            if not _says_why(lines, node):
                hidden.append(f"{_rel(path)}:{node.lineno}")
    assert not hidden, (f"{len(hidden)} imports inside functions without a '# lazy: why' "
                        f"comment: {hidden[:40]}")
    assert modules


def _says_why(lines: list[str], node: ast.AST) -> bool:
    """A '# lazy:' comment on the import's lines or in the comment block just above it."""
    said = lines[node.lineno - 1:node.end_lineno]
    row = node.lineno - 2
    while row >= 0 and lines[row].lstrip().startswith("#"):
        said.append(lines[row])
        row -= 1
    return any("# lazy:" in line for line in said)


def _in_top_block(tree: ast.Module, node: ast.AST) -> bool:
    """Inside a top-level `if`/`try` (TYPE_CHECKING, optional dependencies)."""
    for top in tree.body:
        if isinstance(top, (ast.If, ast.Try)) and any(n is node for n in ast.walk(top)):
            return True
    return False


@pytest.mark.parametrize("folder", ["core", "worker", "service", "native", "docs", "tests",
                                    "deploy"])
def test_nothing_but_benchmarks_refers_to_the_shared_folder(folder):
    pattern = re.compile(r"\.\./shared|shared/DESIGN\.md|shared/STYLE\.md")
    files = [p for p in (ROOT / folder).rglob("*") if p.is_file()
             and p.suffix in (".py", ".md", ".yml", ".yaml", ".txt", ".js", ".html", ".toml")]
    files += [ROOT / "README.md", ROOT / "Makefile"] if folder == "docs" else []
    # docs/benchmarks.md records benchmark runs on the optional data, as the benchmarks do.
    hits = [_rel(p) for p in files if p != Path(__file__) and _rel(p) != "docs/benchmarks.md"
            and pattern.search(p.read_text())]
    assert not hits, f"refer to docs/design.md (or benchmarks' optional data) instead: {hits}"


@pytest.mark.parametrize("argv", [["--help"], ["serve", "--help"], ["keys", "list"],
                                  ["worker", "--help"]])
def test_the_command_line_loads_torch_only_for_a_command_that_needs_it(argv):
    code = (f"import sys, core.cli; core.cli.build_parser({argv!r}); "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert out.stdout.strip() == "False", out.stderr
    code = "import sys, core.cli; core.cli.build_parser(['mesh']); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert out.stdout.strip() == "True", out.stderr  # the check can see torch


def test_test_modules_have_unique_names():
    """pytest imports test files by their base name (rootdir mode, no __init__.py): two with
    the same name stop the whole run at collection."""
    names: dict[str, list[str]] = {}
    for path in (ROOT / "tests").rglob("test_*.py"):
        names.setdefault(path.name, []).append(_rel(path))
    assert not {n: p for n, p in names.items() if len(p) > 1}
