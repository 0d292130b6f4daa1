"""`/docs`: Swagger UI served by the service itself (assets vendored in `app/api/static/swagger-ui/`).

FastAPI's own page loads Swagger UI from a public CDN and its favicon from the web, so on an air-gapped
robot network it was blank. This page is FastAPI's, pointed at the vendored files under `/docs/assets/`
(relative to the root path the service is mounted at), with Swagger UI's validator badge (an image from
the web) turned off. The OAuth2 redirect page FastAPI serves with it is inline HTML. ReDoc, which FastAPI
would load from a CDN along with a web font, is not served.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

SWAGGER_UI_DIR = Path(__file__).resolve().parent / "static" / "swagger-ui"
DOCS_PATH = "/docs"
ASSETS_PATH = "/docs/assets"
OAUTH2_REDIRECT_PATH = "/docs/oauth2-redirect"


def install_docs(app: FastAPI) -> None:
    """Serve `/docs`, its OAuth2 redirect page and the vendored assets (create the app with `docs_url=None`
    and `redoc_url=None`, so that FastAPI's CDN pages are not served)."""
    app.mount(ASSETS_PATH, StaticFiles(directory=SWAGGER_UI_DIR), name="swagger-ui")

    async def swagger_ui(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "").rstrip("/")
        spec = app.openapi_url or "/openapi.json"
        return get_swagger_ui_html(
            openapi_url=f"{root}{spec}",
            title=f"{app.title} - Swagger UI",
            swagger_js_url=f"{root}{ASSETS_PATH}/swagger-ui-bundle.js",
            swagger_css_url=f"{root}{ASSETS_PATH}/swagger-ui.css",
            swagger_favicon_url=f"{root}{ASSETS_PATH}/favicon-32x32.png",
            oauth2_redirect_url=f"{root}{OAUTH2_REDIRECT_PATH}",
            swagger_ui_parameters={"validatorUrl": None},
        )

    async def oauth2_redirect(_: Request) -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    app.add_route(DOCS_PATH, swagger_ui, include_in_schema=False)
    app.add_route(OAUTH2_REDIRECT_PATH, oauth2_redirect, include_in_schema=False)
