"""The HTTP contract: openapi.yaml matches the app, the app answers schema-generated requests
(schemathesis) without a server error and as its schema says, and importing it never imports
torch."""

from __future__ import annotations

import collections
import difflib
import subprocess
import sys
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis.specs.openapi.checks import positive_data_acceptance
from service_harness import make_settings

from service.app import create_app
from service.auth import create_key

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = 40
# The raw-body operations (tus PATCH, zip archive) take bytes like application/octet-stream.
schemathesis.serializer.alias(["application/zip", "application/offset+octet-stream"],
                              "application/octet-stream")


def test_openapi_yaml_is_current():
    from service.openapi import openapi_yaml

    committed = (ROOT / "openapi.yaml").read_text()
    current = openapi_yaml()
    if committed != current:
        diff = "".join(list(difflib.unified_diff(committed.splitlines(True),
                                                 current.splitlines(True), "openapi.yaml",
                                                 "the app"))[:60])
        pytest.fail("openapi.yaml differs from the app; regenerate it with\n"
                    "  .venv/bin/python -m service.openapi > openapi.yaml\n"
                    f"and review the change:\n{diff}")


def test_the_api_process_never_imports_torch():
    code = ("import sys\nfrom service.app import create_app\nimport service.commands, "
            "service.serve, service.openapi\nfrom service.routers import *\n"
            "assert 'torch' not in sys.modules, 'torch was imported'\n"
            "assert 'native' not in sys.modules\nprint('ok')")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


# `EXAMPLES` generated requests an operation, no shrinking: bounded time.
GENERATED = settings(max_examples=EXAMPLES, deadline=None, database=None,
                     suppress_health_check=list(HealthCheck),
                     phases=[Phase.explicit, Phase.generate])


def _schema(app, key: str):
    """The app's schema, every request it generates sending `key`."""
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)

    @schema.auth()
    class BearerKey:
        def get(self, case, ctx):
            return key

        def set(self, case, data, ctx):
            case.headers = {**(case.headers or {}), "Authorization": f"Bearer {data}"}

    return schema


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    s = make_settings(tmp_path_factory.mktemp("schemathesis") / "data",
                      commit_wait_seconds=1.0)
    app = create_app(s)
    _, key = create_key(s.database, "fuzz")
    return app, key


@pytest.mark.parametrize("mode", ["positive", "negative"])
def test_no_server_errors_and_responses_match_the_schema(api, mode):
    """Every operation, `EXAMPLES` generated requests each (valid ones, then invalid ones):
    no 5xx, and status, headers, content type and body as openapi.yaml says."""
    from schemathesis.generation import GenerationMode

    app, key = api
    schema = _schema(app, key)
    failures, statuses = [], collections.Counter()
    for result in schema.get_all_operations():
        operation = result.ok()

        @given(case=operation.as_strategy(GenerationMode(mode), auth_storage=schema.auth))
        @GENERATED
        def check(case):
            # Schema-valid requests may still be refused by runtime rules a schema cannot state
            # (an unsafe path, a size over the configured limit, a time in the past): 4xx for
            # those is right, so only the check that expects them accepted is left out.
            response = case.call_and_validate(excluded_checks=[positive_data_acceptance])
            statuses[response.status_code] += 1

        try:
            check()
        except Unsatisfiable:  # nothing to make invalid (no parameters, no body)
            assert mode == "negative", operation.path
        except Exception as exc:  # collect every operation's failure, then report them all
            failures.append(f"{operation.method.upper()} {operation.path}: {exc}")
    assert not failures, "\n\n".join(failures)
    if mode == "positive":  # the key was sent and valid requests got through
        assert statuses[401] == 0 and statuses[200] and statuses[201], statuses


# The request models, against objects that exist: generated bodies reach every check behind
# the schema (the capture's frames, the reconstruction's, the devices, the names, the keys).
MODELS = {("POST", "/v1/jobs"): "capture_id", ("POST", "/v1/renders"): "job_id",
          ("POST", "/v1/exports"): "job_id", ("POST", "/v1/captures"): None,
          ("PATCH", "/v1/captures/{capture_id}/manifest"): None}


@pytest.fixture(scope="module")
def objects(api, synth_capture):
    """(a ready capture, a capture still uploading, a succeeded reconstruction) of the key's
    tenant."""
    from fastapi.testclient import TestClient
    from service_harness import capture_files, manifest_of, upload_file

    from worker.store import Owner

    app, key = api
    auth = {"Authorization": f"Bearer {key}"}
    files = capture_files(synth_capture)
    with TestClient(app) as client:
        ready, uploading = (client.post("/v1/captures", headers=auth, json={
            "format": "canonical", "manifest": manifest_of(files)}).json()["id"]
            for _ in range(2))
        for path, data in files.items():
            upload_file(client, ready, path, data, auth)
        assert client.post(f"/v1/captures/{ready}/commit", headers=auth).status_code == 200
    store = app.state.services.store
    job = store.create("fuzz", "reconstruct", {}, capture_id=ready)
    owner = Owner.current()
    store.claim(job.id, owner, 5, 3)
    store.finish(job.id, owner, "succeeded")
    return ready, uploading, job.id


@pytest.mark.parametrize("mode", ["positive", "negative"])
def test_request_models_on_real_objects(api, objects, mode):
    """The submits and the manifests, `EXAMPLES` each, their ids pointed at real objects: no
    5xx, answers as the schema says; valid ones get through (202, 201, 200)."""
    from schemathesis.generation import GenerationMode

    app, key = api
    ready, uploading, job = objects
    schema = _schema(app, key)
    failures, statuses = [], collections.Counter()
    for result in schema.get_all_operations():
        operation = result.ok()
        where = (operation.method.upper(), operation.path)
        if where not in MODELS:
            continue

        @given(case=operation.as_strategy(GenerationMode(mode), auth_storage=schema.auth))
        @GENERATED
        def check(case):
            field = MODELS[(case.operation.method.upper(), case.operation.path)]
            path = (case.path_parameters or {}).get("capture_id")
            if isinstance(path, str) and 1 <= len(path) <= 64:
                case.path_parameters["capture_id"] = uploading
            value = case.body.get(field) if field and isinstance(case.body, dict) else None
            if isinstance(value, str) and 1 <= len(value) <= 64:  # not what a negative case broke
                case.body[field] = ready if field == "capture_id" else job
            response = case.call_and_validate(excluded_checks=[positive_data_acceptance])
            statuses[response.status_code] += 1
            assert response.status_code < 500, response.text

        try:
            check()
        except Exception as exc:
            failures.append(f"{where[0]} {where[1]}: {exc}")
    assert not failures, "\n\n".join(failures)
    assert not [s for s in statuses if s >= 500], statuses
    if mode == "positive":
        assert statuses[202] and statuses[201], statuses
