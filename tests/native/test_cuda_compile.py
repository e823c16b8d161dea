"""The CUDA kernels compile with nvcc, and their launchers link, without a GPU or a CUDA torch.

Every `native/csrc/*.cu` is compiled for one architecture (sm_90), in parallel, into a temporary
folder; then a host-only C++ file that includes every `*_cuda.h` launcher header (as the op's .cpp
will under DGS_WITH_CUDA) and takes the address of every launcher instantiation is compiled and
linked against those objects, which catches a header the host compiler rejects and a launcher
declared but never instantiated. Running the kernels needs a GPU (see native/csrc/CUDA.md).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

CSRC = Path(__file__).resolve().parents[2] / "native" / "csrc"
NVCC = shutil.which("nvcc")
FLAGS = ["-std=c++17", "-O3", "-arch=sm_90", "-I", str(CSRC)]
EXPECTED = {"projection.cu", "intersect.cu", "rasterize.cu", "raytrace.cu"}

pytestmark = pytest.mark.skipif(
    NVCC is None, reason="nvcc is not on PATH: the CUDA kernels cannot be compiled here")

# Uses every launcher with every element type it is instantiated for; linking fails if one is
# missing. Nothing runs: main() only checks the addresses.
LINK_PROBE = r"""
#include "intersect_cuda.h"
#include "projection_cuda.h"
#include "rasterize_cuda.h"
#include "raytrace_cuda.h"

#include <cstdio>

template <typename T> int probe() {
  using namespace dgs::cuda;
  const void* fns[] = {
      reinterpret_cast<const void*>(&launch_projection_fwd<T>),
      reinterpret_cast<const void*>(&launch_projection_bwd<T>),
      reinterpret_cast<const void*>(&launch_intersect_sort<T>),
      reinterpret_cast<const void*>(&launch_rasterize_fwd<T>),
      reinterpret_cast<const void*>(&launch_rasterize_bwd<T>),
      reinterpret_cast<const void*>(&launch_trace_visibility<T>),
  };
  int n = 0;
  for (const void* f : fns) n += f != nullptr;
  return n;
}

int main() {
  const void* plain[] = {
      reinterpret_cast<const void*>(&dgs::cuda::intersect_count_temp_bytes),
      reinterpret_cast<const void*>(&dgs::cuda::launch_intersect_count),
      reinterpret_cast<const void*>(&dgs::cuda::intersect_sort_temp_bytes),
  };
  int n = probe<float>() + probe<double>();
  for (const void* f : plain) n += f != nullptr;
  std::printf("%d\n", n);
  return n == 15 ? 0 : 1;
}
"""


def _run(cmd: list[str]) -> tuple[list[str], int, str, float]:
    t0 = time.monotonic()
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=110)
    return cmd, out.returncode, out.stdout + out.stderr, time.monotonic() - t0


def _own_warnings(output: str) -> list[str]:
    """Warnings nvcc reports in this project's sources (not in CUB or system headers)."""
    return [line for line in output.splitlines()
            if re.search(r"warning", line, re.IGNORECASE) and str(CSRC) in line]


def test_cuda_sources_compile_and_link(tmp_path):
    sources = sorted(CSRC.glob("*.cu"))
    assert EXPECTED <= {s.name for s in sources}, f"missing CUDA sources in {CSRC}"
    cmds = [[NVCC, "-c", *FLAGS, str(s), "-o", str(tmp_path / (s.stem + ".o"))] for s in sources]
    probe = tmp_path / "link_probe.cpp"
    probe.write_text(LINK_PROBE)
    cmds.append([NVCC, "-c", "-x", "c++", "-std=c++17", "-I", str(CSRC), str(probe), "-o",
                 str(tmp_path / "link_probe.o")])
    with ThreadPoolExecutor(max_workers=len(cmds)) as pool:
        results = list(pool.map(_run, cmds))
    for cmd, rc, output, seconds in results:
        print(f"{Path(cmd[-3]).name}: rc={rc} in {seconds:.1f}s")
        assert rc == 0, f"nvcc failed on {cmd[-3]}:\n{' '.join(cmd)}\n{output}"
        assert not _own_warnings(output), f"nvcc warned on {cmd[-3]}:\n{output}"
    objects = [str(tmp_path / (s.stem + ".o")) for s in sources]
    exe = tmp_path / "link_probe"
    cmd, rc, output, seconds = _run([NVCC, "-arch=sm_90", str(tmp_path / "link_probe.o"),
                                     *objects, "-o", str(exe)])
    print(f"link: rc={rc} in {seconds:.1f}s")
    assert rc == 0, f"linking the launchers failed:\n{' '.join(cmd)}\n{output}"
    assert exe.exists()
