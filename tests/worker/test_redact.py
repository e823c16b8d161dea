"""worker.redact: server folders written the way a client knows the files."""

from __future__ import annotations

from worker.redact import SERVER, redact


def test_paths_under_roots_become_relative_or_labelled():
    roots = [("/srv/dgs/store/captures/cap_1", ""), ("/srv/dgs", SERVER)]
    text = ("cannot decode '/srv/dgs/store/captures/cap_1/images/000000/cam03.png'; "
            "scratch /srv/dgs/work/jobs/j/run; /srv/dgs; /srv/dgs-other/x; "
            "/srv/dgs/store/captures/cap_1")
    assert redact(text, roots) == (
        "cannot decode 'images/000000/cam03.png'; scratch <server>/work/jobs/j/run; <server>; "
        "/srv/dgs-other/x; .")
    assert redact("nothing here", roots) == "nothing here"
    assert redact("/srv/dgs/x", [(None, ""), ("/srv/dgs/", SERVER)]) == "<server>/x"
