"""Imports go one way: service -> worker (contract only) -> core -> native (docs/design.md section 2),
and the API process (service) never imports torch directly (tests/test_structure.py follows the
imports transitively)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("native", "core", "worker", "service")
# What each package may not import (directly, anywhere in its modules).
FORBIDDEN = {
    "native": {"core", "worker", "service"},
    "core": {"worker", "service"},
    "worker": {"service"},
    "service": {"torch", "native"},
}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


def _modules(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


@pytest.mark.parametrize("package", PACKAGES)
def test_imports_go_one_way(package):
    bad = {}
    for path in _modules(package):
        hit = _imports(path) & FORBIDDEN[package]
        if hit:
            bad[str(path.relative_to(ROOT))] = sorted(hit)
    assert not bad, f"{package} imports what it may not: {bad}"


def test_checker_sees_violations(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("import torch\nfrom core.model import x\nfrom . import sibling\n")
    assert _imports(probe) == {"torch", "core"}


# Queries live in the job store (`worker.api_queries`), never in the routers nor in the lookups
# and checks they call (issue 40): no SQLAlchemy, no session of the store's.
NO_QUERIES = ("service/routers", "service/lookups.py", "service/checks.py",
              "service/pagination.py")


def _runs_queries(path: Path) -> bool:
    return "sqlalchemy" in _imports(path) or ".session(" in path.read_text()


def test_routers_run_no_queries():
    paths = [p for where in NO_QUERIES for p in
             ((ROOT / where).rglob("*.py") if (ROOT / where).is_dir() else [ROOT / where])]
    assert len(paths) > 10
    bad = [str(p.relative_to(ROOT)) for p in paths if _runs_queries(p)]
    assert not bad, f"queries outside the job store (move them to worker/api_queries.py): {bad}"


def test_query_check_sees_a_query(tmp_path):
    for code in ("from sqlalchemy import select\n", "with store.session() as s:\n    pass\n"):
        (probe := tmp_path / "probe.py").write_text(code)
        assert _runs_queries(probe)
