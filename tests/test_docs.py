"""Every command in README.md and docs/api.md runs as written.

The fenced ```sh and ```python blocks of each file run in document order in one bash session
(`set -eu`) from the repository root; consecutive python blocks form one script run by the
venv's interpreter (as pasted into one `.venv/bin/python`). Two substitutions only: port
8000 becomes a free port (tests run side by side), and the session is killed at the end.

A block that must not run in a test says so in its info string, ```sh norun, and the line
before it is an HTML comment giving the reason (`<!-- norun: ... -->`). NORUN_BUDGET keeps
that set small: today `make demo` / `make test` (minutes; the suite itself) and the
foreground `dgs serve` of the README (runs until stopped; docs/api.md runs it in the
background)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from live_server import ROOT, clean_env, free_port

FENCE = re.compile(r"^```(\w*)([^\n]*)\n(.*?)^```\s*$", re.M | re.S)
RUN = {"sh", "bash", "shell", "python"}
NORUN_BUDGET = {"README.md": 2, "docs/api.md": 0}
pytestmark = pytest.mark.timeout(600)


def blocks(path: Path) -> list[tuple[str, str, bool, str]]:
    """(language, code, runs, text before the block) of each fenced block."""
    text = path.read_text()
    out = []
    for m in FENCE.finditer(text):
        lang, info, code = m.group(1), m.group(2).split(), m.group(3)
        before = text[:m.start()].rstrip().rsplit("\n", 1)[-1]
        out.append((lang, code, lang in RUN and "norun" not in info, before))
    return out


def script(path: Path, port: int) -> str:
    """The file's runnable blocks as one bash script."""
    lines = ["set -eu", "trap 'kill $(jobs -p) 2>/dev/null || true' EXIT"]
    python: list[str] = []

    def flush():
        if python:
            lines.extend([f"'{sys.executable}' - <<'DGS_DOCS_PY'", *python, "DGS_DOCS_PY"])
            python.clear()

    for lang, code, runs, _ in blocks(path):
        if not runs:
            continue
        code = code.replace("8000", str(port))
        if lang == "python":
            python.append(code)
        else:
            flush()
            lines.append(code)
    flush()
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("name", sorted(NORUN_BUDGET))
def test_norun_blocks_are_few_and_explained(name):
    skipped = [(lang, before) for lang, _, runs, before in blocks(ROOT / name)
               if lang in RUN and not runs]
    assert len(skipped) <= NORUN_BUDGET[name], skipped
    for lang, before in skipped:
        assert before.startswith("<!-- norun:"), f"{name}: a ```{lang} norun block needs a " \
                                                 f"'<!-- norun: reason -->' line before it"


@pytest.mark.parametrize("name", sorted(NORUN_BUDGET))
def test_every_command_runs_as_written(name, tmp_path):
    path = ROOT / name
    assert any(runs for _, _, runs, _ in blocks(path)), f"{name} has no runnable block"
    port = free_port()
    body = script(path, port)
    (tmp_path / "script.sh").write_text(body)
    env = clean_env(tmp_path / "unused-data")
    env.pop("DGS_DATA_DIR")
    env["TMPDIR"] = str(tmp_path)  # the walkthrough's mktemp -d lands here
    out = subprocess.run(["bash", str(tmp_path / "script.sh")], cwd=ROOT, env=env, text=True,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=540)
    print(out.stdout[-4000:])
    assert out.returncode == 0, f"{name}: a block failed (script: {tmp_path / 'script.sh'}):\n" \
                                f"{out.stdout[-6000:]}"
    if name == "docs/api.md":
        assert '"state":"succeeded"' in out.stdout, out.stdout[-3000:]
        assert "401" in out.stdout
