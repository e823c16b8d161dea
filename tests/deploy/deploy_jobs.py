"""Tiny jobs for the bring-up test: synthetic captures of 32x32 pictures and training schedules
of a few hundred steps (what is checked is the deployment, not the method)."""

from __future__ import annotations

from pathlib import Path

from compose_stack import Stack


def tiny_config(iterations: int) -> dict:
    """Every training stage, densification, a reset and the AO bake, in `iterations` steps."""
    f = iterations / 100
    stages = {"stage2_start": 30, "stage3_start": 70, "densify_from": 5, "densify_until": 60,
              "densify_interval": 10, "reset_interval": 40, "sh_interval": 10}
    schedule = {"iterations": iterations, **{k: max(1, round(v * f)) for k, v in stages.items()}}
    return {"train": {"schedule": schedule, "init_points": 300}}


def synth(folder: Path, frames: int, seed: int) -> Path:
    """A synthetic capture of `frames` frames, 8 views of 32x32, with its ground truth."""
    from core.synth import SynthConfig, synthesize  # lazy: torch, on the test's side only

    synthesize(folder, SynthConfig(frames=frames, views=8, width=32, height=32, seed=seed,
                                   ao_directions=8))
    return folder


def worker_hosts(stack: Stack) -> dict[str, str]:
    """{hostname: container id} of the running worker containers (a job's `worker` is
    hostname/pid, and a container's hostname is its id's start)."""
    return {stack.hostname(c["ID"]): c["ID"] for c in stack.containers("worker")}
