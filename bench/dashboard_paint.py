"""First paint of the dashboard on a 1M-voxel session: how long after navigation the heat map is drawn.

One `vlmap serve` process (model-free grounding, in-memory sessions, API keys on) and Debian's headless
Chromium driven by selenium. A session on the ScanNet scene scene0590_00 gets the voxel size that makes its
grid closest to 1M voxels, and an utterance. Each run first fuses an observation batch (a new version, as
a robot would make: its summary is computed by the batch's answer, its top-down view is not) and then loads
`/dashboard#session=<id>` in a fresh navigation; the figure is the page's `vlmap:heatmap` performance mark
(set once the heat map, the summary panels and the scene graph's outlines are drawn), in ms from the
navigation's start. Prints JSON; asserts nothing. `--screenshot PATH` then sends one more utterance and
saves the page once it shows it (docs/dashboard.png, quantised to 256 colours to stay small).

The browser helpers here are the browser test's too (tests/test_dashboard_browser.py).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import statistics
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import httpx
import numpy as np

from app.api.auth import digest, new_key
from app.belief.grid import VoxelGrid
from app.client import VLMapClient
from app.scene_graph.model import SceneGraph
from app.sim.service import MODEL_FREE_ENV, running_service

if TYPE_CHECKING:
    from selenium.webdriver.chrome.webdriver import WebDriver

SCENES = Path(__file__).resolve().parent.parent / "tests" / "resources" / "scenes"
SCENE = SCENES / "scannet_scene0590_00.json"
#: The grounding and store settings of a quick service: no model to load, nothing written to disk.
QUICK_SERVICE = {
    **MODEL_FREE_ENV,
    "VLMAP_DATA_DIR": "",
    "VLMAP_RATE_LIMIT_PER_S": "0",
}
#: Where the browser's proxy points: a loopback port nothing listens on (the discard port), so every request
#: to an address other than loopback fails at once, and none leaves the machine.
DEAD_PROXY = "http://127.0.0.1:9"
#: The sessionStorage entry where the dashboard keeps the key (app/api/static/dashboard/dashboard.js).
KEY_ENTRY = "vlmap.viewerKey"


def browser_paths() -> tuple[str, str] | None:
    """(chromium, chromedriver) as Debian installs them (`apt-get install chromium chromium-driver`)."""
    chromium, driver = shutil.which("chromium"), shutil.which("chromedriver")
    return (chromium, driver) if chromium and driver else None


def headless_chromium(chromium: str, chromedriver: str, width: int = 1400, height: int = 1000) -> WebDriver:
    """Headless Chromium that reaches loopback only (`DEAD_PROXY`), with its network log kept (CDP
    `Network.*` events in the "performance" log) so that a test can list every request the page made."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in (
        "--headless=new",
        "--no-sandbox",  # as root, in a container
        "--disable-dev-shm-usage",
        "--disable-gpu",
        f"--window-size={width},{height}",
        f"--proxy-server={DEAD_PROXY}",  # loopback addresses bypass a proxy: all else goes nowhere
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-default-apps",
        "--disable-sync",
        "--no-first-run",
    ):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"performance": "ALL", "browser": "ALL"})
    # Given the driver's path, selenium looks for nothing else (its manager would try the network).
    return webdriver.Chrome(options=options, service=Service(executable_path=chromedriver))


def requested_urls(driver: WebDriver) -> list[str]:
    """The URLs of the requests the browser sent since the last call (its performance log), but for those of
    data: and blob: URLs, which reach no address."""
    urls = []
    for entry in driver.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        if message["method"] == "Network.requestWillBeSent":
            url = message["params"]["request"]["url"]
            if not url.startswith(("data:", "blob:")):
                urls.append(url)
    return urls


def service_keys() -> tuple[dict[str, str], str, str]:
    """(env, viewer key, robot key): a service with a viewer key and a key for robots "robot-7" and
    "robot-9"."""
    viewer, robot = new_key(), new_key()
    records = [
        {"name": "dashboard", "role": "viewer", "sha256": digest(viewer)},
        {"name": "robot-7", "role": "robot", "sha256": digest(robot), "robot_ids": ["robot-7", "robot-9"]},
    ]
    return {"VLMAP_API_KEYS": json.dumps(records)}, viewer, robot


def million_voxel_grid(scene: dict[str, Any], target: int = 1_000_000) -> dict[str, float]:
    """The grid spec (voxel size, default margin) whose grid around the scene is closest to `target` voxels,
    sizes in whole millimetres."""
    graph = SceneGraph.model_validate(scene)
    sizes = np.arange(0.030, 0.120, 0.001)
    counts = [VoxelGrid.around(graph, voxel_size=float(s)).n_voxels for s in sizes]
    best = float(sizes[int(np.argmin([abs(c - target) for c in counts]))])
    return {"voxel_size": round(best, 3)}


def first_paint(driver: WebDriver, url: str, session_id: str, timeout_s: float) -> dict[str, float]:
    """Load the dashboard on one session in a fresh navigation; ms from its start to the heat map's mark
    and to the first contentful paint (the key form's header)."""
    from selenium.webdriver.support.ui import WebDriverWait

    driver.get("about:blank")
    driver.get(f"{url}/dashboard#session={session_id}")
    marks = "return performance.getEntriesByName('vlmap:heatmap').map((m) => m.startTime)"
    WebDriverWait(driver, timeout_s).until(lambda d: d.execute_script(marks))
    heat = float(driver.execute_script(marks)[0])
    paints = driver.execute_script(
        "return performance.getEntriesByType('paint').map((p) => [p.name, p.startTime])"
    )
    return {"heatmap_ms": heat, **{f"{name}_ms": float(at) for name, at in paints}}


def screenshot(driver: WebDriver, client: VLMapClient, session_id: str, path: Path) -> None:
    """Give the fleet a second robot's session, say one more thing to the session, wait for the page to draw
    it and save the page as a PNG."""
    from PIL import Image
    from selenium.webdriver.support.ui import WebDriverWait

    rooms = json.loads((SCENES / "two_rooms.json").read_text(encoding="utf-8"))
    other = client.create_session("robot-9", rooms, target_label="backpack")["id"]
    client.send_utterance(other, "I left my backpack on the table in the kitchen")
    version = client.send_utterance(session_id, "maybe I left the keys on a chair")["belief"]["version"]
    shown = f"return document.getElementById('detail').dataset.version === '{version}'"
    WebDriverWait(driver, 60).until(lambda d: d.execute_script(shown))
    driver.set_window_size(1400, 1150)  # the utterance history too
    png = Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB")
    png.quantize(256).save(path, optimize=True)


def spread(values: list[float]) -> dict[str, float]:
    return {
        "median": round(statistics.median(values), 1),
        "min": round(min(values), 1),
        "max": round(max(values), 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--voxels", type=int, default=1_000_000, help="Grid size to aim for")
    parser.add_argument("--screenshot", type=Path, help="Save a PNG of the page after the runs")
    args = parser.parse_args()
    paths = browser_paths()
    if paths is None:
        msg = "needs Debian's chromium and chromium-driver (apt-get install chromium chromium-driver)"
        raise SystemExit(msg)
    scene = json.loads(SCENE.read_text(encoding="utf-8"))
    env, viewer, robot = service_keys()
    driver = None
    with running_service({**QUICK_SERVICE, **env}) as url:
        try:
            client = VLMapClient(url, api_key=robot, timeout_s=120.0)
            grid = million_voxel_grid(scene, args.voxels)
            session = client.create_session("robot-7", scene, target_label="keys", grid=grid)
            sid = session["id"]
            client.send_utterance(sid, "I left my keys on the nightstand")
            rng = np.random.default_rng(0)
            shape = session["grid"]["shape"]
            driver = headless_chromium(*paths)
            driver.get(f"{url}/dashboard")
            driver.execute_script(f"sessionStorage.setItem('{KEY_ENTRY}', arguments[0])", viewer)
            runs = []
            for _ in range(args.runs):
                voxels = rng.integers(0, shape, size=(2000, 3))
                client.send_observations(sid, voxels=voxels, labels=["floor"] * len(voxels))
                runs.append(first_paint(driver, url, sid, timeout_s=120.0))
            if args.screenshot is not None:
                screenshot(driver, client, sid, args.screenshot)
            topdown = httpx.get(
                f"{url}/v1/sessions/{sid}/belief/topdown",
                headers={"Authorization": f"Bearer {viewer}"},
                timeout=60,
            )
            report = {
                "voxels": session["grid"]["n_voxels"],
                "grid_shape": shape,
                "voxel_size_m": grid["voxel_size"],
                "topdown_bytes": len(topdown.content),
                "cpus": os.cpu_count(),
                "runs": args.runs,
                "heatmap_ms": spread([r["heatmap_ms"] for r in runs]),
                "first_contentful_paint_ms": spread([r["first-contentful-paint_ms"] for r in runs]),
                "each_heatmap_ms": [round(r["heatmap_ms"], 1) for r in runs],
                "when": time.strftime("%Y-%m-%d %H:%M:%S"),
            }
            print(json.dumps(report, indent=2))
        finally:
            if driver is not None:
                driver.quit()


if __name__ == "__main__":
    main()
