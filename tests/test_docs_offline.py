"""`/docs` works without the internet: its page loads only the service's own assets, which are vendored with
their licence; and the OpenAPI document carries request examples for every operation that takes input."""

from __future__ import annotations

import fnmatch
import json
import re
import tomllib
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.api.app import create_app
from app.api.auth import digest, new_key
from app.api.docs import SWAGGER_UI_DIR
from app.api.examples import BODY_EXAMPLES
from tests.conftest import model_free_settings

ROOT = Path(__file__).resolve().parent.parent
COMMITTED = ROOT / "openapi" / "openapi.json"
CONTENT_TYPES = {
    ".js": ("text/javascript", "application/javascript"),
    ".css": ("text/css",),
    ".png": ("image/png",),
}


class _Assets(HTMLParser):
    """The URLs a page loads: scripts, stylesheets, icons, images, frames."""

    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []
        self.scripts = 0

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        values = dict(attrs)
        if tag == "script":
            self.scripts += 1
        for name in ("src", "href"):
            url = values.get(name)
            if url is not None and tag in ("script", "link", "img", "iframe", "source"):
                self.urls.append(url)


def page_assets(html: str) -> _Assets:
    parser = _Assets()
    parser.feed(html)
    return parser


def test_docs_load_only_the_service_own_assets(client: TestClient) -> None:
    page = client.get("/docs")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assets = page_assets(page.text)
    assert len(assets.urls) == 3 and assets.scripts == 2  # the bundle, the stylesheet, the icon; the setup
    for url in assets.urls:
        assert url.startswith("/") and not url.startswith("//"), url  # on this host, whatever its name
        answer = client.get(url)
        assert answer.status_code == 200, url
        kind = answer.headers["content-type"].split(";")[0].strip()
        assert kind in CONTENT_TYPES[Path(url).suffix], (url, kind)
        assert answer.content == (SWAGGER_UI_DIR / Path(url).name).read_bytes()
    assert not re.search(r"https?:|//[a-z]", page.text, re.IGNORECASE)  # no absolute URL anywhere on the page
    assert "'/openapi.json'" in page.text and '"validatorUrl": null' in page.text  # no validator badge image
    redirect = client.get("/docs/oauth2-redirect")
    assert redirect.status_code == 200 and not page_assets(redirect.text).urls
    assert client.get("/redoc").status_code == 404  # FastAPI's ReDoc page would load a CDN and a web font


def test_docs_follow_the_root_path_of_a_proxy() -> None:
    with TestClient(create_app(model_free_settings()), root_path="/vlmap") as client:
        page = client.get("/docs")
        urls = page_assets(page.text).urls
        assert urls and all(url.startswith("/vlmap/docs/assets/") for url in urls), urls
        assert "'/vlmap/openapi.json'" in page.text


def test_docs_need_no_key_where_the_api_does() -> None:
    settings = model_free_settings(
        api_keys=json.dumps([{"name": "v", "role": "viewer", "sha256": digest(new_key())}])
    )
    with TestClient(create_app(settings)) as client:
        assert client.get("/v1/sessions").status_code == 401
        page = client.get("/docs")
        assert page.status_code == 200
        assert all(client.get(url).status_code == 200 for url in page_assets(page.text).urls)


def test_the_vendored_assets_carry_their_licence_and_origin() -> None:
    files = sorted(path.name for path in SWAGGER_UI_DIR.iterdir())
    assert files == [
        "LICENSE",
        "NOTICE",
        "README.md",
        "favicon-32x32.png",
        "swagger-ui-bundle.js",
        "swagger-ui-bundle.js.LICENSE.txt",
        "swagger-ui.css",
    ]
    assert "Apache License" in (SWAGGER_UI_DIR / "LICENSE").read_text(encoding="utf-8")
    readme = (SWAGGER_UI_DIR / "README.md").read_text(encoding="utf-8")
    version = re.search(r"`swagger-ui-dist`, version \*\*([0-9.]+)\*\*", readme)
    assert version is not None
    assert f'"{version.group(1)}"' in (SWAGGER_UI_DIR / "swagger-ui-bundle.js").read_text(encoding="utf-8")
    assert sum(path.stat().st_size for path in SWAGGER_UI_DIR.iterdir()) < 2_500_000  # no source maps
    # The wheel ships them: every vendored file matches a package-data pattern of the app package.
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"][
        "package-data"
    ]["app"]
    for path in SWAGGER_UI_DIR.iterdir():
        relative = path.relative_to(ROOT / "app").as_posix()
        assert any(fnmatch.fnmatch(relative, pattern) for pattern in patterns), relative


def _operations() -> list[tuple[str, str, dict[str, Any]]]:
    spec = json.loads(COMMITTED.read_text(encoding="utf-8"))
    return [
        (method.upper(), path, op)
        for path, methods in spec["paths"].items()
        for method, op in methods.items()
    ]


@pytest.mark.parametrize(
    ("method", "path", "op"), _operations(), ids=lambda v: v if isinstance(v, str) else ""
)
def test_every_operation_that_takes_input_has_request_examples(
    method: str, path: str, op: dict[str, Any]
) -> None:
    for media, content in op.get("requestBody", {}).get("content", {}).items():
        if media == "application/json" or media.endswith("+json"):
            assert content.get("examples"), f"{method} {path}: no example of its {media} body"
            for name, example in content["examples"].items():
                assert example.get("summary") and "value" in example, (method, path, name)
    for parameter in op.get("parameters", []):
        if parameter["in"] == "path":
            assert parameter.get("examples"), f"{method} {path}: no example of {parameter['name']}"
    takes_input = op.get("requestBody") or op.get("parameters")
    if takes_input:
        named = [p for p in op.get("parameters", []) if p.get("examples")]
        assert named or op.get("requestBody"), f"{method} {path}: no example of any input"


def test_the_body_examples_are_accepted(client: TestClient) -> None:
    """Every JSON body example is valid: the stateless operations answer 200, a new session 201 (and the
    examples of the session routes then work on it)."""
    for name, example in BODY_EXAMPLES["ground"].items():
        assert client.post("/v1/ground", json=example["value"]).status_code == 200, name
    for name, example in BODY_EXAMPLES["normalize_scene_graph"].items():
        assert client.post("/v1/scene-graphs/normalize", json=example["value"]).status_code == 200, name
    sessions = {}
    for name, example in BODY_EXAMPLES["create_session"].items():
        created = client.post("/v1/sessions", json=example["value"])
        assert created.status_code == 201, (name, created.text)
        sessions[name] = created.json()["id"]
    sid, with_labels = sessions["two_rooms"], sessions["label_map"]
    for name, example in BODY_EXAMPLES["add_utterance"].items():
        assert client.post(f"/v1/sessions/{sid}/utterances", json=example["value"]).status_code == 200, name
    for name, example in BODY_EXAMPLES["add_observations"].items():
        target = with_labels if name == "voxels" else sid
        answer = client.post(f"/v1/sessions/{target}/observations", json=example["value"])
        assert answer.status_code == 200, (name, answer.text)
        assert answer.json()["voxels_updated"] > 0, name
    for name, example in BODY_EXAMPLES["replace_scene_graph"].items():
        assert client.put(f"/v1/sessions/{sid}/scene-graph", json=example["value"]).status_code == 200, name
