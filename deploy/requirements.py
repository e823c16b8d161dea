"""Print the project's requirements, its dependencies and those of the named extras, one a line,
from pyproject.toml, for `pip install -r` and `pip wheel -r`.

    python3 requirements.py pyproject.toml train worker

The images install these in a layer of their own before the code is copied in, so that a change
of the code rebuilds only the layers after it (the packages, torch above all, stay cached); and
deploy/offline.sh makes its wheelhouse from the same list. Standard library only: it runs on the
image's bare Python.
"""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path


def requirements(pyproject: Path, extras: list[str]) -> list[str]:
    """The dependencies of `pyproject` and of its `extras`, in order, each once."""
    project = tomllib.loads(pyproject.read_text())["project"]
    optional = project.get("optional-dependencies", {})
    unknown = [e for e in extras if e not in optional]
    if unknown:
        raise ValueError(f"{pyproject}: no extra named {', '.join(unknown)}; it has "
                         f"{', '.join(sorted(optional))}")
    lines = list(project["dependencies"]) + [r for e in extras for r in optional[e]]
    return list(dict.fromkeys(lines))


def main(argv: list[str]) -> int:
    if not argv:
        print("usage: requirements.py PYPROJECT [EXTRA ...]", file=sys.stderr)
        return 2
    try:
        print("\n".join(requirements(Path(argv[0]), argv[1:])))
    except (OSError, KeyError, ValueError) as exc:
        print(f"requirements.py: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
