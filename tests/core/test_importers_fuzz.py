"""Every importer (panoptic, transforms, COLMAP text and binary, IDR, ActorsHQ) and the canonical
capture.json's validation on mutated files (tests/fuzz_sources.py): whatever the mutation, a
reader either imports or raises CaptureError whose every problem has a message and names a
file of the source; nothing else escapes. A bounded run (derandomized, so the suite is
repeatable); `benchmarks/fuzz_importers.py --examples 10000` is the long one."""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core.synth import SynthConfig, synthesize

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from fuzz_sources import make_sources, mutated_copy, run_importer  # noqa: E402

KINDS = ("panoptic", "transforms", "colmap-text", "colmap-binary", "idr", "actorshq",
         "canonical")
EXAMPLES = 100
"""Per source kind: 700 in all, about 30 s on the 2-core dev machine (loaded)."""


@pytest.fixture(scope="module")
def sources(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("fuzz")
    synthesize(root / "capture", SynthConfig(frames=2, views=3, width=16, height=16, seed=1,
                                             ao_directions=4, supersample=1))
    return root, make_sources(root / "capture", root / "sources")


def test_every_source_imports_unmutated(sources):
    root, found = sources
    assert sorted(found) == sorted(KINDS)
    for kind, source in found.items():
        assert run_importer(source, source.root, root / f"plain-{kind}") == ("imported", "")


@pytest.mark.parametrize("kind", KINDS)
def test_mutated_sources_raise_nothing_but_capture_errors(sources, kind):
    root, found = sources
    outcomes: list[str] = []

    @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow])
    @given(seed=st.integers(0, 2**32 - 1))
    def check(seed: int) -> None:
        work = Path(tempfile.mkdtemp(dir=root))
        try:
            folder, done = mutated_copy(found[kind], work / "src", seed)
            outcome, what = run_importer(found[kind], folder, work / "out")
            outcomes.append(outcome)
            assert outcome != "unexpected", f"seed {seed}, {done}:\n{what}"
        finally:
            shutil.rmtree(work, ignore_errors=True)

    check()
    assert len(outcomes) == EXAMPLES and "refused" in outcomes  # the mutations do bite
