"""Just-in-time build of the C++ extension, on first use only.

The build folder is keyed by a fingerprint of the sources, the flags, and the torch and Python
versions, so an edit rebuilds and an unchanged tree loads the cached library. Importing
`native` never builds; `load()` does, once per process.

Processes that load at once (a test run, several workers) build once: the build runs under an
flock on `build.lock` in the folder, which the kernel releases when its holder dies. torch's own
lock file (`lock`, which it only ever waits on) is therefore stale whenever we hold the flock (a
build killed mid-way left it) and is removed, instead of hanging every later process. A finished
build writes `built`; later processes import the library directly, without running ninja.
"""

from __future__ import annotations

import fcntl
import hashlib
import importlib.util
import os
import sys
import threading
from pathlib import Path
from types import ModuleType

__all__ = ["NativeBuildError", "load", "build_dir", "fingerprint", "SOURCES"]

_CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES: tuple[str, ...] = ("ext.cpp", "projection.cpp", "intersect.cpp", "rasterize.cpp",
                            "raytrace.cpp")
_CFLAGS: tuple[str, ...] = ("-O3", "-fopenmp", "-std=c++17")
_LDFLAGS: tuple[str, ...] = ("-fopenmp",)

_lock = threading.Lock()
_module: ModuleType | None = None


class NativeBuildError(RuntimeError):
    """The C++ extension failed to compile or load; the message carries the compiler's output."""


def fingerprint() -> str:
    import torch

    h = hashlib.sha256()
    # What the build compiles: its sources and every header they could include.
    paths = [_CSRC / s for s in SOURCES] + sorted(_CSRC.glob("*.h"))
    for path in paths:
        h.update(path.name.encode())
        h.update(path.read_bytes() if path.exists() else b"<missing>")
    h.update(repr((_CFLAGS, _LDFLAGS, torch.__version__, sys.version_info[:2])).encode())
    return h.hexdigest()[:16]


def build_dir() -> Path:
    """Where builds are cached: $DGS_NATIVE_BUILD_DIR, else build/native beside the sources when
    writable (a checkout), else ~/.cache/dgs/native (an installed package)."""
    env = os.environ.get("DGS_NATIVE_BUILD_DIR")
    if env:
        return Path(env)
    repo_build = _CSRC.parent.parent / "build" / "native"
    try:
        repo_build.mkdir(parents=True, exist_ok=True)
        if os.access(repo_build, os.W_OK):
            return repo_build
    except OSError:
        pass
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "dgs" / "native"


def _import_built(out: Path, name: str) -> ModuleType | None:
    """The library a finished build left in `out` (its `built` marker names it), else None."""
    marker = out / "built"
    if not marker.is_file():
        return None
    library = out / marker.read_text().strip()
    if not library.is_file():
        return None
    import torch  # noqa: F401  (the extension links against libtorch, loaded by this import)

    spec = importlib.util.spec_from_file_location(name, library)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def load(verbose: bool = False) -> ModuleType:
    """Build (first time) and import the extension; raises NativeBuildError on failure."""
    global _module
    if _module is not None:
        return _module
    with _lock:
        if _module is not None:
            return _module
        fp = fingerprint()
        name = f"dgs_native_{fp}"
        out = build_dir() / fp
        out.mkdir(parents=True, exist_ok=True)
        _module = _import_built(out, name)
        if _module is not None:
            return _module
        with open(out / "build.lock", "a") as held:
            fcntl.flock(held, fcntl.LOCK_EX)  # another process's build: wait for it
            _module = _import_built(out, name)
            if _module is None:
                _module = _build(out, name, verbose)
        return _module


def _build(out: Path, name: str, verbose: bool) -> ModuleType:
    """Compile and import (the caller holds the folder's flock)."""
    from torch.utils import cpp_extension

    (out / "lock").unlink(missing_ok=True)  # torch's baton, left by a build that was killed
    try:
        module = cpp_extension.load(
            name=name,
            sources=[str(_CSRC / s) for s in SOURCES],
            extra_cflags=list(_CFLAGS),
            extra_ldflags=list(_LDFLAGS),
            extra_include_paths=[str(_CSRC)],
            build_directory=str(out),
            verbose=verbose,
        )
    except Exception as exc:  # the compiler's message is in str(exc)
        raise NativeBuildError(
            f"building the native rasterizer in {out} failed.\n{exc}\n"
            "Check that a C++17 compiler (g++) and ninja are installed, or pass "
            "backend='reference' to use the plain PyTorch implementation."
        ) from exc
    tmp = out / "built.tmp"
    tmp.write_text(Path(module.__file__).name + "\n")
    os.replace(tmp, out / "built")
    return module
