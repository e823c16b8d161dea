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
