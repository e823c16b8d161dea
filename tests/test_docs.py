"""Every command in README.md and docs/api.md runs as written, and the documents keep their shape.

The fenced ```sh and ```python blocks of each file run in document order in one bash session
(`set -eu`) from the repository root; consecutive python blocks form one script run by the
venv's interpreter (as pasted into one `.venv/bin/python`). Two substitutions only: port
8000 becomes a free port (tests run side by side), and the session is killed at the end.

A block that must not run in a test says so in its info string, ```sh norun, and the line
before it is an HTML comment giving the reason (`<!-- norun: ... -->`). NORUN_BUDGET keeps
that set small: today `make demo` / `make test` (minutes; the suite itself) and the
foreground `dgs serve` of the README (runs until stopped; docs/api.md runs it in the
background).

The shape (docs/decisions/README.md says how to add to it): README.md and docs/design.md stay under
their page limits, every relative link in README.md and docs/ reaches an existing file and, when
it names one, an existing heading; every decision record is dated, has the four sections and is
listed in the index; every benchmarks.md section is dated and read."""

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
PAGE_LIMITS = {"README.md": 200, "docs/design.md": 700}  # issue 40: a page a newcomer reads
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$", re.M)
RECORD_NAME = re.compile(r"^\d{4}-\d{2}-\d{2}-[a-z0-9-]+\.md$")
RECORD_SECTIONS = ("## Context", "## Decision", "## Measurements", "## Consequences")
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


def prose(text: str) -> str:
    """The text without fenced blocks and inline code: what a reader sees as links and headings."""
    text = re.sub(r"^```.*?^```\s*$", "", text, flags=re.M | re.S)
    return re.sub(r"`[^`\n]*`", "", text)


def anchors(path: Path) -> set[str]:
    """GitHub's heading ids: lower case, punctuation dropped, spaces to hyphens, repeats -1, -2."""
    seen: dict[str, int] = {}
    out = set()
    text = re.sub(r"^```.*?^```\s*$", "", path.read_text(), flags=re.M | re.S)
    for m in HEADING.finditer(text):
        title = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", m.group(2))
        slug = re.sub(r"[^\w\- ]", "", title.lower().replace("`", "")).replace(" ", "-")
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def documents() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


@pytest.mark.parametrize("name", sorted(PAGE_LIMITS))
def test_pages_stay_short(name):
    lines = (ROOT / name).read_text().count("\n")
    assert lines <= PAGE_LIMITS[name], (
        f"{name} has {lines} lines, the limit is {PAGE_LIMITS[name]}: move the narrative into a "
        f"dated record under docs/decisions/ and keep one sentence with a link here")


@pytest.mark.parametrize("path", documents(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(path):
    broken = []
    for target in LINK.findall(prose(path.read_text())):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, mailto:, ...
            continue
        file, _, anchor = target.partition("#")
        dest = (path.parent / file).resolve() if file else path
        if not dest.exists():
            broken.append(f"{target}: no file {dest.relative_to(ROOT) if dest.is_relative_to(ROOT) else dest}")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading '#{anchor}' in {dest.relative_to(ROOT)}")
    assert not broken, f"{path.relative_to(ROOT)}:\n" + "\n".join(broken)


def test_decision_records_are_dated_whole_and_indexed():
    folder = ROOT / "docs" / "decisions"
    index = (folder / "README.md").read_text()
    records = sorted(p for p in folder.glob("*.md") if p.name != "README.md")
    assert records, "docs/decisions/ holds no record"
    for record in records:
        assert RECORD_NAME.match(record.name), f"{record.name}: name it YYYY-MM-DD-<slug>.md"
        text = record.read_text()
        missing = [s for s in RECORD_SECTIONS if not re.search(f"^{s}$", text, re.M)]
        assert not missing, f"{record.name} lacks {missing}"
        assert re.search(r"^- \*\*Date:\*\* " + record.name[:10], text, re.M), \
            f"{record.name}: its Date line must be the date in its name"
        assert f"]({record.name})" in index, f"{record.name} is not listed in docs/decisions/README.md"


def test_benchmark_sections_are_dated_and_read():
    text = (ROOT / "docs" / "benchmarks.md").read_text()
    sections = re.split(r"^## ", prose(text), flags=re.M)[1:]
    names = [s.split("\n", 1)[0] for s in sections]
    assert names[-1] == "Still to measure", "\"Still to measure\" stays the last section"
    for section in sections[:-1]:
        name = section.split("\n", 1)[0]
        assert re.search(r"\b20\d\d-\d\d-\d\d\b", section), f"benchmarks.md, {name}: no date"
        assert "\nReading:" in section, f"benchmarks.md, {name}: no 'Reading:' of its table"
    still = sections[-1]
    assert 0 <= still.find("**On the CPU:**") < still.find("**On a GPU**"), \
        "\"Still to measure\" lists the CPU's first and what needs a GPU at its end"
