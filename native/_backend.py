"""Just-in-time build of the C++ extension, on first use only.

The build folder is keyed by a fingerprint of the sources, the flags, and the torch and Python
versions, so an edit rebuilds and an unchanged tree loads the cached library. Importing
`native` never builds; `load()` does, once per process.
"""

from __future__ import annotations

import hashlib
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


def load(verbose: bool = False) -> ModuleType:
    """Build (first time) and import the extension; raises NativeBuildError on failure."""
    global _module
    if _module is not None:
        return _module
    with _lock:
        if _module is not None:
            return _module
        from torch.utils import cpp_extension

        fp = fingerprint()
        out = build_dir() / fp
        out.mkdir(parents=True, exist_ok=True)
        try:
            _module = cpp_extension.load(
                name=f"dgs_native_{fp}",
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
        return _module
