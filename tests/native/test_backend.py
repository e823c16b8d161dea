"""Building the extension: never on import, cached by fingerprint, one clear error on failure."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import native._backend as backend

REPO = Path(__file__).resolve().parents[2]


def test_import_never_builds(tmp_path):
    code = ("import os, native, native.reference, core; "
            "print(sorted(os.listdir(os.environ['DGS_NATIVE_BUILD_DIR'])))")
    env = dict(os.environ, DGS_NATIVE_BUILD_DIR=str(tmp_path / "b"), PYTHONPATH=str(REPO))
    (tmp_path / "b").mkdir()
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_fingerprint_follows_sources(tmp_path, monkeypatch):
    for name in backend.SOURCES:
        (tmp_path / name).write_text("// a\n")
    monkeypatch.setattr(backend, "_CSRC", tmp_path)
    first = backend.fingerprint()
    assert backend.fingerprint() == first
    (tmp_path / "rasterize.cpp").write_text("// b\n")
    assert backend.fingerprint() != first
    second = backend.fingerprint()
    (tmp_path / "new_header.h").write_text("// c\n")
    assert backend.fingerprint() not in (first, second)


def test_build_dir_override(tmp_path, monkeypatch):
    monkeypatch.setenv("DGS_NATIVE_BUILD_DIR", str(tmp_path / "x"))
    assert backend.build_dir() == tmp_path / "x"


def test_failed_build_raises_one_clear_error(tmp_path, monkeypatch):
    src = tmp_path / "csrc"
    src.mkdir()
    for name in backend.SOURCES:
        (src / name).write_text("#error deliberately broken for the test\n")
    monkeypatch.setattr(backend, "_CSRC", src)
    monkeypatch.setattr(backend, "_module", None)
    monkeypatch.setenv("DGS_NATIVE_BUILD_DIR", str(tmp_path / "build"))
    with pytest.raises(backend.NativeBuildError) as err:
        backend.load()
    message = str(err.value)
    assert "deliberately broken" in message
    assert "backend='reference'" in message


_TINY = '''
#include <pybind11/pybind11.h>
int answer() { return 42; }
PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) { m.def("answer", &answer); }
'''


def _load_in_subprocess(src: Path, build: Path) -> subprocess.CompletedProcess:
    code = ("import sys; from pathlib import Path; import native._backend as b; "
            f"b._CSRC = Path({str(src)!r}); m = b.load(); print(m.answer())")
    env = dict(os.environ, DGS_NATIVE_BUILD_DIR=str(build), PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          timeout=300, cwd=src)


def test_a_build_killed_midway_does_not_hang_the_next_and_a_finished_one_is_reused(tmp_path,
                                                                                  monkeypatch):
    """torch's lock file, left behind by a build that was killed, used to make every later
    load wait forever; a finished build is imported again without running ninja."""
    src = tmp_path / "csrc"
    src.mkdir()
    for name in backend.SOURCES:
        (src / name).write_text(_TINY if name == "ext.cpp" else "// nothing\n")
    monkeypatch.setattr(backend, "_CSRC", src)
    out = tmp_path / "build" / backend.fingerprint()
    out.mkdir(parents=True)
    (out / "lock").write_text("")  # what a SIGKILLed build leaves
    first = _load_in_subprocess(src, tmp_path / "build")
    assert first.returncode == 0, first.stderr
    assert first.stdout.strip() == "42"
    assert not (out / "lock").exists() and (out / "built").is_file()
    # The next process imports the library directly: ninja's files are not needed any more.
    for leftover in ("build.ninja", ".ninja_log", ".ninja_deps"):
        (out / leftover).unlink(missing_ok=True)
    for obj in out.glob("*.o"):
        obj.unlink()
    second = _load_in_subprocess(src, tmp_path / "build")
    assert second.returncode == 0, second.stderr
    assert second.stdout.strip() == "42" and not (out / "build.ninja").exists()
