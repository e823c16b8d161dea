"""Just-in-time build of the C++ extension, on first use only.

The build folder is keyed by a fingerprint of the sources, the flags, and the torch and Python
versions, so an edit rebuilds and an unchanged tree loads the cached library. Importing
`native` never builds; `load()` does, once per process.

Processes that load at once (a test run, several workers) build once: the build runs under an
flock on `build.lock` in the folder, which the kernel releases when its holder dies. torch's own
lock file (`lock`, which it only ever waits on) is therefore stale whenever we hold the flock (a
build killed mid-way left it) and is removed, instead of hanging every later process. A finished
build writes `built`; later processes import the library directly, without running ninja.

CUDA: where torch is a CUDA build that sees a GPU and nvcc is found (torch's CUDA_HOME), the
kernels of `CUDA_SOURCES` and their torch-side wrappers are compiled in too, with
`-DDGS_WITH_CUDA`; the ops then run CUDA tensors on the GPU (`has_cuda()` says which build this
is). The architecture is the visible GPUs' (or $TORCH_CUDA_ARCH_LIST), and it is part of the
fingerprint. `DGS_CUDA=0` builds the CPU library even where CUDA is available.
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

import torch

__all__ = ["NativeBuildError", "load", "build_dir", "fingerprint", "cuda_build", "has_cuda",
           "SOURCES", "CUDA_SOURCES"]

_CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES: tuple[str, ...] = ("ext.cpp", "projection.cpp", "intersect.cpp", "rasterize.cpp",
                            "raytrace.cpp")
CUDA_SOURCES: tuple[str, ...] = ("projection.cu", "intersect.cu", "rasterize.cu", "raytrace.cu",
                                 "projection_cuda.cpp", "intersect_cuda.cpp",
                                 "rasterize_cuda.cpp", "raytrace_cuda.cpp")
_CFLAGS: tuple[str, ...] = ("-O3", "-fopenmp", "-std=c++17")
_LDFLAGS: tuple[str, ...] = ("-fopenmp",)
# nvcc contracts a*b+c into FMA (the CPU build does not): values differ from the CPU op by
# rounding, which the CUDA tests bound; no fast-math (exp and division stay IEEE).
_CUDA_CFLAGS: tuple[str, ...] = ("-O3", "-std=c++17", "-DDGS_WITH_CUDA")

_lock = threading.Lock()
_module: ModuleType | None = None


class NativeBuildError(RuntimeError):
    """The C++ extension failed to compile or load; the message carries the compiler's output."""


def cuda_build() -> bool:
    """Whether `load()` builds (or built) the CUDA kernels in: a CUDA torch that sees a GPU, nvcc
    (torch's CUDA_HOME), and DGS_CUDA not "0"."""
    if os.environ.get("DGS_CUDA", "1") == "0":
        return False

    if torch.version.cuda is None or not torch.cuda.is_available():
        return False
    # lazy: only to build (it imports setuptools)
    from torch.utils import cpp_extension

    return cpp_extension.CUDA_HOME is not None


def has_cuda() -> bool:
    """Whether the loaded extension runs CUDA tensors (builds it if needed)."""
    return bool(load().has_cuda())


def _sources() -> list[str]:
    return list(SOURCES) + (list(CUDA_SOURCES) if cuda_build() else [])


def _cuda_arch() -> str:
    env = os.environ.get("TORCH_CUDA_ARCH_LIST")
    if env:
        return env
    caps = {torch.cuda.get_device_capability(i) for i in range(torch.cuda.device_count())}
    return ";".join(f"{a}.{b}" for a, b in sorted(caps))


def fingerprint() -> str:
    h = hashlib.sha256()
    # What the build compiles: its sources and every header they could include.
    paths = [_CSRC / s for s in _sources()] + sorted(_CSRC.glob("*.h"))
    for path in paths:
        h.update(path.name.encode())
        h.update(path.read_bytes() if path.exists() else b"<missing>")
    h.update(repr((_CFLAGS, _LDFLAGS, torch.__version__, sys.version_info[:2])).encode())
    if cuda_build():
        h.update(repr((_CUDA_CFLAGS, torch.version.cuda, _cuda_arch())).encode())
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
    # lazy: only to build (it imports setuptools)
    from torch.utils import cpp_extension

    (out / "lock").unlink(missing_ok=True)  # torch's baton, left by a build that was killed
    cuda = cuda_build()
    cflags = list(_CFLAGS) + (["-DDGS_WITH_CUDA"] if cuda else [])
    if cuda:
        os.environ.setdefault("TORCH_CUDA_ARCH_LIST", _cuda_arch())
    try:
        module = cpp_extension.load(
            name=name,
            sources=[str(_CSRC / s) for s in _sources()],
            extra_cflags=cflags,
            extra_cuda_cflags=list(_CUDA_CFLAGS) if cuda else None,
            extra_ldflags=list(_LDFLAGS),
            extra_include_paths=[str(_CSRC)],
            build_directory=str(out),
            verbose=verbose,
        )
    except Exception as exc:  # the compiler's message is in str(exc)
        raise NativeBuildError(
            f"building the native rasterizer in {out} failed.\n{exc}\n"
            "Check that a C++17 compiler (g++) and ninja are installed"
            + (" and that nvcc matches torch's CUDA (or set DGS_CUDA=0 for a CPU build)"
               if cuda else "")
            + ", or pass backend='reference' to use the plain PyTorch implementation."
        ) from exc
    tmp = out / "built.tmp"
    tmp.write_text(Path(module.__file__).name + "\n")
    os.replace(tmp, out / "built")
    return module
