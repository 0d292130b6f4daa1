"""`/dashboard`: the fleet dashboard, a page of plain HTML, JavaScript and CSS served by the service itself
(`app/api/static/dashboard/`; no CDN, no web font), so that it works on an air-gapped robot network.

The page needs no key to load: the operator enters a viewer key in it once, the page keeps it in the
browser's sessionStorage (gone with the tab) and sends it with every API call, the push stream included
(read with fetch(), since EventSource cannot send an Authorization header; docs/api.md). Its Content
Security Policy lets it load and call only this origin.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse

from app.errors import NotFound

DASHBOARD_DIR = Path(__file__).resolve().parent.parent / "static" / "dashboard"

_ASSETS = {"dashboard.js": "text/javascript", "dashboard.css": "text/css"}
_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'none'; script-src 'self'; style-src 'self'; connect-src 'self'; img-src 'self'; "
        "base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    ),
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
    "Cache-Control": "no-cache",  # revalidated (ETag), so that an upgraded service serves its new page
}

router = APIRouter(include_in_schema=False)


@router.get("/dashboard")
async def dashboard() -> FileResponse:
    """The dashboard page."""
    return FileResponse(DASHBOARD_DIR / "index.html", media_type="text/html", headers=_HEADERS)


@router.get("/dashboard/{asset}")
async def dashboard_asset(asset: str) -> FileResponse:
    """One of the page's scripts or stylesheets."""
    if asset not in _ASSETS:
        msg = f"no dashboard asset {asset!r}"
        raise NotFound(msg)
    return FileResponse(DASHBOARD_DIR / asset, media_type=_ASSETS[asset], headers=_HEADERS)
