"""The web page's files as the API serves them (no browser needed; tests/e2e drives it in
Chromium): the page and every module it imports are served with the right types and the
security headers, nothing is fetched from another origin (it works offline), and the page never
shadows the API's JSON errors."""

from __future__ import annotations

import re

from service.webpage import WEB_DIR

IMPORT = re.compile(r"""^\s*import\s[^'"]*['"](\./[^'"]+)['"]""", re.M)


def test_the_page_and_its_modules_are_served(client):
    page = client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    csp = page.headers["content-security-policy"]
    assert "script-src 'self'" in csp and "connect-src 'self'" in csp
    assert page.headers["x-content-type-options"] == "nosniff"
    todo, seen = ["js/app.js"], set()
    assert 'src="/web/js/app.js"' in page.text
    while todo:
        rel = todo.pop()
        if rel in seen:
            continue
        seen.add(rel)
        r = client.get(f"/web/{rel}")
        assert r.status_code == 200, rel
        assert "javascript" in r.headers["content-type"], (rel, r.headers["content-type"])
        assert "script-src 'self'" in r.headers["content-security-policy"]
        base = rel.rsplit("/", 1)[0]
        todo += [f"{base}/{m[2:]}" for m in IMPORT.findall(r.text)]
    assert {"js/api.js", "js/tus.js", "js/sha256.js", "js/splat.js", "js/relight.js"} <= seen
    for asset in ("style.css", "favicon.svg"):
        assert client.get(f"/web/{asset}").status_code == 200


def test_nothing_comes_from_another_origin():
    for path in WEB_DIR.rglob("*"):
        if path.is_file():
            text = path.read_text()
            found = re.findall(r"(?:https?:)?//[a-z0-9.-]+\.[a-z]{2,}[/\"']", text, re.I)
            found = [f for f in found if "//www.w3.org/" not in f]  # XML namespace names
            assert not found, f"{path.name} refers to another origin: {found}"


def test_the_api_keeps_its_json_errors(client):
    r = client.get("/v1/nope")
    assert r.status_code == 404 and r.headers["content-type"].startswith("application/json")
    assert client.get("/web/nope.js").status_code == 404
    assert client.get("/?x=1").status_code == 400  # the strict query rule covers the page too
