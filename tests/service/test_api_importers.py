"""Issue 42 through the API: each hostile capture file (tests/hostile_sources.py), sent as a zip
(POST /v1/captures/archive) or uploaded with tus and committed, answers 422 naming the file and
the field, never 500 retryable; a tus capture stays uploading with the error to read, commits
of the same files answer the same 422, and fixing the file makes it ready. An exception an
importer should never raise is answered 422 import_failed, not retryable (the policy:
docs/decisions/2026-11-29-importers-fail-closed.md); a full disk stays 500 retryable."""

from __future__ import annotations

import errno
import hashlib
import logging
import sys
from pathlib import Path

import pytest
from service_harness import ZIP, make_zip, upload_file

from core.data.importers import IMPORTERS, Importer

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from hostile_sources import ATTACKS, attacked, source_files  # noqa: E402




def _named(error: dict, attack) -> None:
    """The answer names the metadata file as the client knows it, and the field."""
    assert error["code"] == "invalid_capture" and error["retryable"] is False, error
    hits = [d for d in error["details"] if d["path"] == attack.file
            and d["message"].startswith(attack.message)]
    assert hits, error["details"]
    assert f"{attack.file}: {attack.message}" in error["message"]


@pytest.mark.parametrize("attack", ATTACKS, ids=lambda a: a.name)
def test_archive_answers_422_naming_file_and_field(client, services, synth_capture, attack):
    body = make_zip(attacked(synth_capture, attack))
    r = client.post("/v1/captures/archive", params={"format": attack.fmt}, content=body,
                    headers=ZIP)
    assert r.status_code == 422, r.text
    _named(r.json()["error"], attack)
    assert client.get("/v1/captures").json()["items"] == []  # nothing kept


def _uploaded(client, new_capture, files: dict[str, bytes], fmt: str) -> str:
    capture = new_capture(files, fmt=fmt)
    for path, data in files.items():
        upload_file(client, capture["id"], path, data)
    return capture["id"]


@pytest.mark.parametrize("attack", ATTACKS, ids=lambda a: a.name)
def test_tus_commit_answers_the_same_422_every_time(client, new_capture, synth_capture,
                                                    attack):
    capture_id = _uploaded(client, new_capture, attacked(synth_capture, attack), attack.fmt)
    first = client.post(f"/v1/captures/{capture_id}/commit")
    assert first.status_code == 422, first.text
    _named(first.json()["error"], attack)
    out = client.get(f"/v1/captures/{capture_id}").json()
    assert out["state"] == "uploading" and out["error"] == first.json()["error"]
    again = client.post(f"/v1/captures/{capture_id}/commit")
    assert (again.status_code, again.json()) == (422, first.json())


def test_a_refused_file_fixed_and_sent_again_commits(client, new_capture, synth_capture):
    attack = ATTACKS[0]  # fn leaves the source
    capture_id = _uploaded(client, new_capture, attacked(synth_capture, attack), attack.fmt)
    assert client.post(f"/v1/captures/{capture_id}/commit").status_code == 422
    good = source_files(synth_capture, attack.fmt)[attack.file]
    r = client.patch(f"/v1/captures/{capture_id}/manifest", json={"files": [
        {"path": attack.file, "size": len(good), "sha256": hashlib.sha256(good).hexdigest()}]})
    assert r.status_code == 200, r.text
    upload_file(client, capture_id, attack.file, good)
    r = client.post(f"/v1/captures/{capture_id}/commit")
    assert r.status_code == 200 and r.json()["summary"]["source_format"] == "panoptic", r.text


def _raising(exc: Exception) -> Importer:
    def read(src):
        raise exc
    panoptic = IMPORTERS["panoptic"]
    return Importer(panoptic.finds, read, panoptic.summary)


def test_an_importer_bug_is_422_import_failed_never_500_retryable(
        client, new_capture, synth_capture, monkeypatch, caplog):
    """The policy for what an importer should never raise: logged with its traceback under a
    reference the answer gives, answered 422 `import_failed` (the same files fail the same
    way: nothing to retry), the capture left uploading; the archive route the same."""
    monkeypatch.setitem(IMPORTERS, "panoptic", _raising(KeyError("cam03")))
    files = source_files(synth_capture, "panoptic")
    capture_id = _uploaded(client, new_capture, files, "panoptic")
    with caplog.at_level(logging.ERROR, logger="dgs.service"):
        r = client.post(f"/v1/captures/{capture_id}/commit")
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["code"] == "import_failed" and error["retryable"] is False
    assert "the panoptic importer failed on these files (KeyError: 'cam03')" in error["message"]
    ref = error["message"].split("logged as ")[1].split(".")[0]
    assert any(ref in rec.getMessage() and rec.exc_info for rec in caplog.records)
    assert client.get(f"/v1/captures/{capture_id}").json()["state"] == "uploading"
    r = client.post("/v1/captures/archive", params={"format": "panoptic"},
                    content=make_zip(files), headers=ZIP)
    assert r.status_code == 422 and r.json()["error"]["code"] == "import_failed", r.text


def test_a_full_disk_is_still_500_retryable(client, new_capture, synth_capture, monkeypatch):
    monkeypatch.setitem(IMPORTERS, "panoptic",
                        _raising(OSError(errno.ENOSPC, "No space left on device")))
    capture_id = _uploaded(client, new_capture, source_files(synth_capture, "panoptic"),
                           "panoptic")
    r = client.post(f"/v1/captures/{capture_id}/commit")
    assert r.status_code == 500 and r.json()["error"]["retryable"] is True, r.text
    assert r.json()["error"]["code"] == "internal"
