"""What a reconstruction may name that lives on the server: a normal-prior model (the tenant's
own `normal_model` asset, checked at upload, or a model the operator allows by name) and a device
(those the deployment offers). Anything else is a 422 before a job exists."""

from __future__ import annotations

import io
import warnings
import zipfile
from pathlib import Path

import pytest
import torch
from service_harness import make_settings
from test_api_assets import exr_bytes

from service.settings import ServiceSettings

PARAMS = {"preset": "test"}


class _Facing(torch.nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(x)


@pytest.fixture
def settings(tmp_path: Path) -> ServiceSettings:
    """A GPU deployment (cuda and cuda:0 offered) with one allow-listed model."""
    return make_settings(tmp_path / "data", devices="auto,cpu,cuda,cuda:0",
                         normal_estimators={"omni": tmp_path / "omni.pt"})


@pytest.fixture
def torchscript(tmp_path: Path) -> bytes:
    path = tmp_path / "facing.pt"
    with warnings.catch_warnings():  # TorchScript is deprecated in torch 2.x, still shipped
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.script(_Facing()).save(str(path))
    return path.read_bytes()


def _zip(names: list[str]) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as z:
        for name in names:
            z.writestr(name, b"x")
    return out.getvalue()


def _upload(client, filename: str, body: bytes, kind: str = "normal_model", headers=None):
    return client.post(f"/v1/assets?kind={kind}&filename={filename}", content=body,
                       headers=headers or {})


def _job(client, capture_id: str, config: dict, headers=None):
    return client.post("/v1/jobs", json={"capture_id": capture_id,
                                         "params": {**PARAMS, "config": config}},
                       headers=headers or {})


@pytest.mark.parametrize("filename, body, words", [
    ("m.pt", b"", "empty"),
    ("m.pt", b"\x00" * 64, "not a TorchScript archive"),
    ("m.pt", _zip(["weights.bin"]), "save the model with torch.jit.save"),
    ("m.onnx", b"PK\x03\x04" + b"\x00" * 60, "not an ONNX model"),
    ("m.exr", b"\x08\x01", "ending in .pt or .ts or .onnx"),
])
def test_a_model_upload_is_checked(client, services, filename, body, words):
    r = _upload(client, filename, body)
    assert r.status_code == 422 and words in r.json()["error"]["message"], r.text
    assert services.blobs.list("assets") == []


def test_a_job_names_its_own_model_asset_or_an_allowed_model(client, tenants, ready_capture,
                                                             torchscript, tmp_path):
    a, b = tenants["a"], tenants["b"]
    capture = ready_capture(a)
    r = _upload(client, "facing.pt", torchscript, headers=a)
    assert r.status_code == 201, r.text
    model = r.json()
    assert model["kind"] == "normal_model"
    onnx = _upload(client, "m.onnx", b"\x08\x07" + b"\x00" * 30, headers=a)
    assert onnx.status_code == 201, onnx.text
    for name in (model["id"], onnx.json()["id"], "omni"):
        r = _job(client, capture, {"normal_estimator": name}, a)
        assert r.status_code == 202, r.text
    # Another tenant's model is no model of yours (404 would tell it exists: same 422).
    other = ready_capture(b)
    refused = _job(client, other, {"normal_estimator": model["id"]}, b)
    assert refused.status_code == 422
    assert refused.json()["error"]["details"][0]["path"] == "params.config.normal_estimator"
    # An envmap is not a model.
    envmap = client.post("/v1/assets?kind=envmap&filename=studio.exr", headers=a,
                         content=exr_bytes(tmp_path))
    assert envmap.status_code == 201, envmap.text
    r = _job(client, capture, {"normal_estimator": envmap.json()["id"]}, a)
    assert r.status_code == 422 and "is a envmap, not a normal_model" in r.text
    # A model a queued job names stays until the job ends.
    r = client.delete(f"/v1/assets/{model['id']}", headers=a)
    assert r.status_code == 409 and "uses asset" in r.text


def test_devices_are_those_the_deployment_offers(client, ready_capture):
    capture = ready_capture()
    for device in ("auto", "cpu", "cuda", "cuda:0"):
        assert _job(client, capture, {"train": {"device": device}}).status_code == 202
    r = _job(client, capture, {"train": {"device": "cuda:1"}})
    assert r.status_code == 422
    assert "offered: auto, cpu, cuda, cuda:0" in r.json()["error"]["message"]
