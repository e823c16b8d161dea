"""Issue 39 through the API (POST /v1/captures/archive): a capture in a mirrored world is ready
with the mirror undone and said in its summary's `import_warnings`; camera-to-world poses in
Panoptic's `w2c` answer 422 naming the file, the field and the fix; an IDR folder with
`images/` and `masks/` is ready; a canonical capture.json's import record of any shape gives
no 500."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from service_harness import ZIP, capture_files, make_zip

from core.data import load_capture

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from rig_sources import Y_DOWN, idr_files, inverted, mirrored, panoptic_files, turned  # noqa: E402




def test_a_mirrored_world_is_ready_and_says_so(client, services, synth_capture):
    body = make_zip(panoptic_files(mirrored(load_capture(synth_capture))))
    r = client.post("/v1/captures/archive", params={"format": "panoptic"}, content=body,
                    headers=ZIP)
    assert r.status_code == 201, r.text
    out = r.json()
    assert out["state"] == "ready" and out["summary"]["cameras"] == 8
    (warning,) = out["summary"]["import_warnings"]
    assert warning.startswith("w2c: every camera's rotation has determinant -1 (a mirrored "
                              "world); the world was mirrored back")
    again = client.get(f"/v1/captures/{out['id']}").json()
    assert again["summary"]["import_warnings"] == [warning]
    stored = load_capture(services.blobs.local_path(f"captures/{out['id']}"))
    assert stored.import_record["warnings"] == [warning]


def test_camera_to_world_poses_in_w2c_answer_422_naming_field_and_fix(client, synth_capture):
    files = panoptic_files(turned(load_capture(synth_capture), Y_DOWN))
    r = client.post("/v1/captures/archive", params={"format": "panoptic"},
                    content=make_zip(inverted(files)), headers=ZIP)
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["code"] == "invalid_capture" and error["retryable"] is False
    (detail,) = error["details"]
    assert detail["path"] == "train_meta.json"
    assert detail["message"].startswith("w2c: these look like camera-to-world poses")
    assert "Invert each matrix" in detail["message"]
    assert client.get("/v1/captures").json()["items"] == []


def test_an_idr_folder_with_images_and_masks_is_ready(client, synth_capture):
    body = make_zip(idr_files(load_capture(synth_capture), plural=True))
    r = client.post("/v1/captures/archive", params={"format": "idr"}, content=body, headers=ZIP)
    assert r.status_code == 201, r.text
    summary = r.json()["summary"]
    assert summary["source_format"] == "idr" and summary["cameras"] == 8
    assert summary["masks"] == 8 and summary["import_warnings"] == []


@pytest.mark.parametrize("record", [["w2c: not ours"], {"warnings": "one string"},
                                    {"warnings": [3, "kept"]}])
def test_a_canonical_import_record_of_any_shape_is_no_500(client, synth_capture, record):
    """capture.json's "import" is the client's JSON: the summary takes only strings from a
    list of warnings, and anything else is none."""
    files = capture_files(synth_capture)
    doc = json.loads(files["capture.json"])
    doc["import"] = record
    files["capture.json"] = json.dumps(doc).encode()
    r = client.post("/v1/captures/archive", content=make_zip(files), headers=ZIP)
    assert r.status_code == 201, r.text
    expected = ["kept"] if isinstance(record, dict) and record["warnings"] == [3, "kept"] else []
    assert r.json()["summary"]["import_warnings"] == expected
