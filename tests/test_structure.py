"""The shape of the code (docs/design.md section 2): modules of at most ~400 lines, functions of
at most ~60 (docstrings aside), no import circle between the project's modules (imports for
types only included), the API process loading no torch through any chain of imports, every
import at the top of its module unless it says why it is lazy (`# lazy: ...` on the line or the
one above), and nothing outside `benchmarks/` referring to the shared folder beside the
repository (a clone has none)."""

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
    """The project modules `path` imports: at its top, inside its functions, and under `if
    TYPE_CHECKING:` (a circle of types is a circle too: neither side stands alone)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        out += _project_modules(node, modules)
    return out


def _project_modules(node: ast.AST, modules: set[str]) -> list[str]:
    """The project modules an import statement names (`from a.b import c` names a.b.c when
    that is a module, else a.b; the project has no relative imports)."""
    names = []
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
        names = [f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules
                 else node.module for a in node.names]
    out = []
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
    assert not _cycles(_graph()), ("these modules import each other (directly, lazily or for "
                                   "types)")


def test_the_cycle_finder_sees_a_circle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


# The API process never loads torch (docs/design.md 2.2): nothing it imports may, through any
# chain of imports that run at import time. These core modules are the ones it relies on.
TORCH_FREE_ROOTS = ("service", "core.config", "core.data.capture", "core.data.schema",
                    "core.data.validate")
TORCH = ("torch", "native")


def _at_import_time(tree: ast.Module):
    """The import statements that run when the module is imported: at its top, in top-level
    `if` (not `if TYPE_CHECKING:`), `try` and `with` blocks and in class bodies; not inside
    functions (lazy) nor under TYPE_CHECKING."""
    stack: list[ast.AST] = list(tree.body)
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, ast.If):
            typing_only = "TYPE_CHECKING" in ast.unparse(node.test)
            stack += node.orelse if typing_only else node.body + node.orelse
        elif isinstance(node, ast.Try):
            stack += node.body + node.orelse + node.finalbody
            stack += [n for h in node.handlers for n in h.body]
        elif isinstance(node, (ast.With, ast.ClassDef)):
            stack += node.body


def _load_graph() -> dict[str, tuple[set[str], set[str]]]:
    """Per project module: (the project modules importing it loads, its own package's and
    theirs included; the outside top-level packages it imports), at import time."""
    paths = {_module_name(p): p for p in _sources()}
    graph = {}
    for name, path in paths.items():
        inside, outside = set(), set()
        for node in _at_import_time(ast.parse(path.read_text())):
            found = _project_modules(node, set(paths))
            inside.update(found)
            if found:
                continue
            if isinstance(node, ast.Import):
                outside.update(a.name.split(".")[0] for a in node.names)
            else:
                outside.add((node.module or "").split(".")[0])
        graph[name] = (inside, outside)
    for name, (inside, _) in graph.items():  # importing a.b.c runs a/__init__ and a/b/__init__
        for module in [name, *inside]:
            parts = module.split(".")
            inside.update(".".join(parts[:i]) for i in range(1, len(parts))
                          if ".".join(parts[:i]) in graph and ".".join(parts[:i]) != name)
    return graph


def _loads(graph: dict[str, tuple[set[str], set[str]]], roots: tuple[str, ...],
           forbidden: tuple[str, ...]) -> dict[str, list[str]]:
    """For each module under `roots` that loads a `forbidden` package, directly or through
    others, the chain of imports that does it."""
    bad = {}
    for root in sorted(m for m in graph if any(m == r or m.startswith(r + ".") for r in roots)):
        seen, queue = {root: [root]}, [root]
        while queue:
            module = queue.pop(0)
            inside, outside = graph[module]
            hit = [f for f in forbidden if f in outside or module.split(".")[0] == f]
            if hit:
                bad[root] = seen[module] + [hit[0]] * (hit[0] in outside)
                break
            for nxt in sorted(inside - set(seen)):
                seen[nxt] = seen[module] + [nxt]
                queue.append(nxt)
    return bad


def test_the_api_process_never_loads_torch_through_any_import():
    bad = _loads(_load_graph(), TORCH_FREE_ROOTS, TORCH)
    assert not bad, "these load torch when imported (make the import lazy, with a '# lazy:' " \
        "reason, or move the code): " + "; ".join(" -> ".join(c) for c in bad.values())


def test_the_transitive_check_sees_a_chain():
    graph = {"service.a": ({"worker.b"}, set()), "worker.b": ({"core.c"}, {"sqlalchemy"}),
             "core.c": (set(), {"torch"}), "service.d": ({"native.e"}, set()),
             "native.e": (set(), {"numpy"}), "service.f": ({"worker.b2"}, set()),
             "worker.b2": (set(), {"numpy"})}
    assert _loads(graph, ("service",), TORCH) == {
        "service.a": ["service.a", "worker.b", "core.c", "torch"],
        "service.d": ["service.d", "native.e"]}
    # The real graph: service.demo loads core.demo (torch) only inside a function.
    real = _load_graph()
    assert "core.demo" not in real["service.demo"][0]
    assert "torch" in real["core.model"][1]


def test_importing_every_api_module_loads_no_torch():
    """The same, as Python does it (third-party packages included)."""
    code = ("import importlib, pkgutil, sys, service\n"
            "for m in pkgutil.walk_packages(service.__path__, 'service.'):\n"
            "    importlib.import_module(m.name)\n"
            "for m in ('core.config', 'core.data.capture', 'core.data.schema', "
            "'core.data.validate'):\n"
            "    importlib.import_module(m)\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'native'}))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", out.stdout


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
    # docs/benchmarks.md and the decision records (docs/decisions/) record benchmark runs on the
    # optional data, as the benchmarks do.
    hits = [_rel(p) for p in files if p != Path(__file__) and _rel(p) != "docs/benchmarks.md"
            and not _rel(p).startswith("docs/decisions/") and pattern.search(p.read_text())]
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


def test_every_name_a_package_exports_exists():
    """`__all__` of each package names what it defines or imports (or serves lazily, `_LAZY`
with a module `__getattr__`), or one of its modules."""
    missing = []
    for init in sorted(p for p in _sources() if p.name == "__init__.py"):
        tree = ast.parse(init.read_text())
        names: list[str] = []
        bound: set[str] = set()
        for node in tree.body:
            if isinstance(node, ast.Assign | ast.AnnAssign):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
                    names = list(ast.literal_eval(node.value))
                if any(isinstance(t, ast.Name) and t.id == "_LAZY" for t in targets):
                    bound.update(ast.literal_eval(node.value))  # served by __getattr__
                bound.update(t.id for t in targets if isinstance(t, ast.Name))
            elif isinstance(node, ast.ImportFrom | ast.Import):
                bound.update((a.asname or a.name).split(".")[0] for a in node.names)
            elif isinstance(node, ast.FunctionDef | ast.ClassDef):
                bound.add(node.name)
        here = init.parent
        missing += [f"{_rel(init)}: {n}" for n in names if n not in bound and not (
            (here / f"{n}.py").is_file() or (here / n / "__init__.py").is_file())]
    assert not missing, f"__all__ names nothing of that name: {missing}"
