"""Shared fixtures: one tiny synthetic capture per session, copied when a test damages it."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest
import torch

from core.synth import SynthConfig, synthesize

TINY = SynthConfig(frames=2, views=8, width=48, height=48, seed=3, priors=True, ao_directions=16)


@pytest.fixture(scope="session")
def synth_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny synthetic capture with priors and ground truth. Read-only by convention."""
    out = tmp_path_factory.mktemp("synth") / "capture"
    synthesize(out, TINY)
    return out


@pytest.fixture
def capture_copy(synth_capture: Path, tmp_path: Path) -> Path:
    """A private copy of the synthetic capture (without gt/) that a test may break."""
    dst = tmp_path / "capture"
    shutil.copytree(synth_capture, dst, ignore=shutil.ignore_patterns("gt"))
    return dst


@pytest.fixture
def tiny_config() -> SynthConfig:
    """The configuration ``synth_capture`` was generated with."""
    return TINY


@pytest.fixture
def digest():
    """``digest(root)``: a hash of a folder tree, to prove something was not modified."""
    return tree_digest


def tree_digest(root: Path) -> str:
    """Hash of every path, file content and symlink target under root."""
    h = hashlib.sha256()
    for path in sorted(root.rglob("*")):
        h.update(str(path.relative_to(root)).encode())
        if path.is_symlink():
            h.update(b"->" + str(path.readlink()).encode())
        elif path.is_file():
            h.update(path.read_bytes())
    return h.hexdigest()


@pytest.fixture
def one_thread():
    # Tiny tensors: a second intra-op thread only adds synchronisation (and on a shared machine
    # a lot of it).
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# A shortened `test` preset (every stage, densification, a reset and the AO bake in 100 steps),
# as in test_pipeline.py; one frame.
TINY_RUN = {"train": {"schedule": {"iterations": 100, "stage2_start": 30, "stage3_start": 70,
                                   "densify_from": 5, "densify_until": 60, "densify_interval": 10,
                                   "reset_interval": 40, "sh_interval": 10},
                      "init_points": 500},
            "gop": 1}


@pytest.fixture(scope="session")
def tiny_run(synth_capture: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished one-frame run of ``synth_capture`` (meshes included). Read-only by convention:
    tests relight and mesh it into their own folders."""
    from core.pipeline import reconstruct

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("tiny_run") / "run"
    try:
        reconstruct(synth_capture, out, preset="test", frames="0:1", overrides=TINY_RUN,
                    progress=False)
    finally:
        torch.set_num_threads(before)
    return out
