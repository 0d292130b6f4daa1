"""Hostile inputs against a real `vlmap serve` (issue 16): every class of the adversarial run, generated from
a seed, against every endpoint, in JSON and msgpack, while /healthz is polled; figures printed, nothing
asserted (tests/test_abuse.py asserts on its own run).

    python -m bench.abuse [--per-class N] [--seed S] [--json FILE]

Classes: label bombs (H1), long lists of bad items (H2), huge overlapping places (H3), label-map id bombs
(H4), huge finite coordinates, deep JSON, non-ASCII digits in label ids, hostile msgpack shapes, bodies
that are not UTF-8 (each a 500 if unguarded), and the low findings (JSON labels that are not ids, unknown
class names, uint8 labels, trailing slashes with a forged Host, integer object ids, Spark-DSG binaries,
whole-grid downloads at once). Every rejected request aimed at the watched session is followed by a check
that its belief (layers and version) is unchanged. Printed: answers per class and status, 5xx, beliefs
changed by a reject, the service's resident memory (before, after, peak) and the largest growth one request
caused, and /healthz latency over the run and while the heaviest requests run.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import random
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import msgpack
import numpy as np

from app.sim.service import MODEL_FREE_ENV, start_service, wait_ready

RESOURCES = Path(__file__).resolve().parent.parent / "tests" / "resources"
#: A service on the model-free parts, no rate limit, and grids small enough that a session's layers (state,
#: not amplification) stay a few MiB: what the run measures is the work hostile requests cause.
SERVICE_ENV = {
    **MODEL_FREE_ENV,
    "VLMAP_DATA_DIR": "",
    "VLMAP_RATE_LIMIT_PER_S": "0",
    "VLMAP_MAX_GRID_VOXELS": "2000000",
}
JSON = {"content-type": "application/json"}
MSGPACK = {"content-type": "application/msgpack"}
#: Characters that str.isdigit() accepts and int() may not (or that are not the ASCII digits an id needs).
ODD_DIGITS = "²³¹٠١٢٣٤٥٦٧٨٩۰۱۲۳߀߁०१२३৪৫"


@dataclass(frozen=True)
class Hostile:
    """One request: its class, method, path (with {sid} for the watched session), body and headers."""

    kind: str
    method: str
    path: str
    body: bytes = b""
    headers: dict[str, str] = field(default_factory=dict)

    @property
    def watched(self) -> bool:
        """Whether it is aimed at the watched session (its belief is checked after a reject)."""
        return "{sid}" in self.path


def scene() -> dict[str, Any]:
    return json.loads((RESOURCES / "scenes" / "two_rooms.json").read_text())


def packed(array: np.ndarray) -> dict[str, Any]:
    return {"dtype": array.dtype.str, "shape": list(array.shape), "data": array.tobytes()}


def _json(value: Any) -> bytes:
    return json.dumps(value, separators=(",", ":")).encode()


def _session(rng: random.Random, graph: Any, **extra: Any) -> dict[str, Any]:
    return {"robot_id": f"abuse-{rng.randrange(10**6)}", "scene_graph": graph, **extra}


def label_bombs(rng: random.Random) -> Iterator[Hostile]:
    """H1: one long class name among many short ones (a fixed-width array of them is n x the longest)."""
    while True:
        n = rng.randrange(2, 5000)
        labels = [rng.choice(["floor", "backpack", "wall", "x"]) for _ in range(n)]
        labels[rng.randrange(n)] = "x" * rng.randrange(257, 400_000)
        body = {"voxels": packed(np.ones((n, 3), np.int32)), "labels": labels}
        yield Hostile(
            "H1 label bomb", "POST", "/v1/sessions/{sid}/observations", msgpack.packb(body), MSGPACK
        )


_BAD_ITEMS = [1, "x", None, [], {}, True, [1, 2], {"id": 1}]


def bad_lists(rng: random.Random) -> Iterator[Hostile]:
    """H2: a long list of bad items somewhere in a JSON body (each item was one error, echoed)."""
    graph = scene()
    while True:
        items = [rng.choice(_BAD_ITEMS)] * rng.randrange(1000, 150_000)
        where = rng.randrange(6)
        if where == 0:
            body, path = {"scene_graph": {"objects": items}, "utterance": "x"}, "/v1/ground"
        elif where == 1:
            body, path = {"scene_graph": {"objects": [], "regions": items}, "utterance": "x"}, "/v1/ground"
        elif where == 2:
            body, path = {"scene_graph": graph, "utterance": "x", "query_points": items}, "/v1/ground"
        elif where == 3:
            body, path = _session(rng, {"objects": items}), "/v1/sessions"
        elif where == 4:
            body, path = {"voxels": items, "labels": items}, "/v1/sessions/{sid}/observations"
        else:
            body, path = {"objects": items}, "/v1/sessions/{sid}/scene-graph"
        method = "PUT" if path.endswith("scene-graph") else "POST"
        yield Hostile("H2 bad list", method, path, _json(body), JSON)


def big_places(rng: random.Random) -> Iterator[Hostile]:
    """H3: many large overlapping boxes on a fine grid (their place index had taken GBs)."""
    while True:
        side = rng.uniform(2, 30)
        objects = [
            {"id": str(i), "label": "table", "center": [0, 0, 2], "size": [side, side, rng.uniform(1, 4)]}
            for i in range(rng.randrange(1, 80))
        ]
        grid = {"voxel_size": rng.choice([0.05, 0.1, 0.2])}
        body = _session(rng, {"objects": objects}, grid=grid, target_label="table")
        yield Hostile("H3 places", "POST", "/v1/sessions", _json(body), JSON)


def label_id_bombs(rng: random.Random) -> Iterator[Hostile]:
    """H4: huge label ids (a dense lookup table would take max id + 1 entries per session)."""
    graph = scene()
    while True:
        ids = {
            str(rng.randrange(2**33)): rng.choice(["backpack", "floor"]) for _ in range(rng.randrange(1, 20))
        }
        ids[str(rng.randrange(2**32))] = "backpack"
        yield Hostile(
            "H4 label ids", "POST", "/v1/sessions", _json(_session(rng, graph, label_map=ids)), JSON
        )


def huge_coordinates(rng: random.Random) -> Iterator[Hostile]:
    """Finite but huge numbers (squares overflow in the grounders): centres, sizes, corners, query points."""
    graph = scene()
    while True:
        big = rng.choice([1, -1]) * 10 ** rng.uniform(5.1, 308)
        victim = json.loads(json.dumps(graph))
        where = rng.randrange(5)
        if where < 2:
            target = rng.choice(victim["objects"] if where == 0 else victim["regions"])
            target[rng.choice(["center", "size"])][rng.randrange(3)] = abs(big)
            path = rng.choice(["/v1/ground", "/v1/sessions", "/v1/sessions/{sid}/scene-graph"])
            if path == "/v1/ground":
                body: Any = {"scene_graph": victim, "utterance": "the bag on the table"}
            elif path == "/v1/sessions":
                body = _session(rng, victim)
            else:
                body = victim
        elif where == 2:
            body, path = (
                {"scene_graph": graph, "utterance": "on the table", "query_points": [[big, 0, 0]]},
                "/v1/ground",
            )
        elif where == 3:
            grid = {"min_corner": [-big, 0, 0], "max_corner": [big, 1, 1]}
            body, path = _session(rng, graph, grid=grid), "/v1/sessions"
        else:
            body, path = {"points": [[big, big, big]], "labels": ["floor"]}, "/v1/sessions/{sid}/observations"
        method = "PUT" if path.endswith("scene-graph") else "POST"
        yield Hostile("huge coordinates", method, path, _json(body), JSON)


_JSON_PATHS = [
    ("POST", "/v1/ground"),
    ("POST", "/v1/sessions"),
    ("POST", "/v1/sessions/{sid}/utterances"),
    ("POST", "/v1/sessions/{sid}/observations"),
    ("PUT", "/v1/sessions/{sid}/scene-graph"),
    ("POST", "/v1/scene-graphs/normalize"),
]


def deep_json(rng: random.Random) -> Iterator[Hostile]:
    """Deeply nested JSON (a recursive decoder's RecursionError would be a 500)."""
    while True:
        depth = rng.randrange(300, 200_000)
        opener, closer = rng.choice([(b"[", b"]"), (b'{"a":', b"}")])
        method, path = rng.choice(_JSON_PATHS)
        body = opener * depth + b"1" + closer * depth
        yield Hostile("deep JSON", method, path, body, JSON)


def odd_digits(rng: random.Random) -> Iterator[Hostile]:
    """Label ids of digits int() refuses or that are not ASCII (str.isdigit() had let them through)."""
    graph = scene()
    while True:
        key = "".join(rng.choice(ODD_DIGITS + "0123456789") for _ in range(rng.randrange(1, 12)))
        body = _session(rng, graph, label_map={key: "backpack"}, target_label="backpack")
        yield Hostile("odd digits", "POST", "/v1/sessions", _json(body), JSON)


def msgpack_shapes(rng: random.Random) -> Iterator[Hostile]:
    """Shapes of packed arrays: bools, negatives, floats, products that overflow, wrong ranks, strings."""
    shapes: list[Callable[[], Any]] = [
        lambda: [True, 3],
        lambda: [rng.randrange(2**63), 3],
        lambda: [6148914691236517206, 3],
        lambda: [-rng.randrange(1, 100), 3],
        lambda: [rng.random() * 10, 3],
        lambda: [rng.randrange(10), 3, 1],
        lambda: "x" * rng.randrange(5),
        lambda: [rng.randrange(2**64)],
        lambda: [],
    ]
    while True:
        dtype = rng.choice(["<i4", "<i8", "|u1", "<f4", ">i4", "object", "<U8", ""])
        data = bytes(rng.randrange(256) for _ in range(rng.choice([0, 8, 12, 24, 48])))
        field = rng.choice(["voxels", "points", "labels", "p_target"])
        body: dict[str, Any] = {field: {"dtype": dtype, "shape": rng.choice(shapes)(), "data": data}}
        if field in ("voxels", "points"):
            body["labels"] = ["floor"]
        else:
            body["voxels"] = packed(np.ones((1, 3), np.int32))
        yield Hostile(
            "msgpack shape", "POST", "/v1/sessions/{sid}/observations", msgpack.packb(body), MSGPACK
        )


def not_utf8(rng: random.Random) -> Iterator[Hostile]:
    """Bytes that are not UTF-8, under every content type, on every endpoint that reads a body."""
    types = [
        None,
        "application/json",
        "text/plain",
        "application/x-www-form-urlencoded",
        "application/msgpack",
    ]
    while True:
        method, path = rng.choice(_JSON_PATHS)
        body = bytes([0xFF, 0xFE]) + bytes(rng.randrange(128, 256) for _ in range(rng.randrange(1, 4000)))
        kind = rng.choice(types)
        yield Hostile("not UTF-8", method, path, body, {"content-type": kind} if kind else {})


def low_findings(rng: random.Random) -> Iterator[Hostile]:
    """The low findings: labels that are not ids, unknown names, uint8 labels, trailing slashes with a forged
    Host, integer object ids."""
    while True:
        pick = rng.randrange(6)
        if pick == 0:
            labels = [rng.choice([True, False, 1.0, 0.5, "floor", 1, None])] * rng.randrange(1, 50)
            body = _json({"voxels": [[1, 1, 1]] * len(labels), "labels": labels})
            yield Hostile("low: labels", "POST", "/v1/sessions/{sid}/observations", body, JSON)
        elif pick == 1:
            name = rng.choice(["spaceship", "!!", "", "x" * 200, "floor" * 3])
            body = _json({"voxels": [[2, 2, 2]], "labels": [name]})
            yield Hostile("low: unknown names", "POST", "/v1/sessions/{sid}/observations", body, JSON)
        elif pick == 2:
            labels = np.array([rng.randrange(2)], np.uint8)
            body = msgpack.packb(
                {"voxels": packed(np.array([[3, 3, 3]], np.int32)), "labels": packed(labels)}
            )
            yield Hostile("low: uint8 labels", "POST", "/v1/sessions/{sid}/observations", body, MSGPACK)
        elif pick == 3:
            path = rng.choice(["/v1/sessions/", "/v1/ground/", "/v1/models/", "/v1/sessions/{sid}/"])
            yield Hostile(
                "low: trailing slash", "GET", path, headers={"host": f"evil{rng.randrange(99)}.example"}
            )
        elif pick == 4:
            objects = [
                {"id": rng.randrange(10**9), "label": "table", "center": [0, 0, 0.4], "size": [1, 1, 0.8]}
            ]
            body = _json({"scene_graph": {"objects": objects}, "utterance": "the bag is on the table"})
            yield Hostile("low: integer ids", "POST", "/v1/ground", body, JSON)
        else:
            yield Hostile("low: grid download", "GET", "/v1/sessions/{sid}/belief?format=grid&layers=true")


def queries(rng: random.Random) -> Iterator[Hostile]:
    """The other endpoints: hostile paths, query strings and methods (listing, reading, polling, deleting,
    the models, probes and metrics)."""
    ids = ["..", "%2e%2e", "x" * 5000, "é", "%00", "a/b", "-", "%ff%fe"]
    params = [
        "robot_id=" + "x" * rng.randrange(1, 3000),
        "robot_id=%00",
        "top_k=-1",
        "top_k=99999999999999999999",
        "format=grid&format=summary",
        "layers=maybe",
        "format=" + "g" * 300,
        "unknown=1",
        "summary=" + "y" * 100,
    ]
    while True:
        sid = rng.choice(ids)
        method, path = rng.choice(
            [
                ("GET", "/v1/sessions?" + rng.choice(params)),
                ("GET", f"/v1/sessions/{sid}"),
                ("GET", f"/v1/sessions/{sid}/belief?" + rng.choice(params)),
                ("GET", "/v1/sessions/{sid}/belief?" + rng.choice(params)),
                ("DELETE", f"/v1/sessions/{sid}"),
                ("GET", "/v1/models?" + rng.choice(params)),
                ("GET", rng.choice(["/healthz", "/readyz", "/metrics"]) + "?" + rng.choice(params)),
                (
                    rng.choice(["PATCH", "PUT", "DELETE"]),
                    rng.choice(["/v1/ground", "/v1/models", "/healthz"]),
                ),
            ]
        )
        headers = {"if-none-match": rng.choice(['"v1"', "*", "x" * 2000, '"v' + "9" * 50 + '"'])}
        yield Hostile("queries and paths", method, path, headers=headers)


def binaries(rng: random.Random) -> Iterator[Hostile]:
    """Spark-DSG binaries: bytes behind a valid opening (each decode is a child process)."""
    while True:
        body = bytes([0xDD, 1, 0, 0, 0]) + bytes(rng.randrange(256) for _ in range(rng.randrange(8, 2000)))
        yield Hostile(
            "M2 binary decode",
            "POST",
            "/v1/scene-graphs/normalize",
            body,
            {"content-type": "application/octet-stream"},
        )


CLASSES: dict[str, Callable[[random.Random], Iterator[Hostile]]] = {
    "H1": label_bombs,
    "H2": bad_lists,
    "H3": big_places,
    "H4": label_id_bombs,
    "coordinates": huge_coordinates,
    "deep": deep_json,
    "digits": odd_digits,
    "shapes": msgpack_shapes,
    "utf8": not_utf8,
    "low": low_findings,
    "queries": queries,
    "binary": binaries,
}
#: Inputs of the costly classes, per `per_class` of the others (each decode is a child process).
SHARE = {"binary": 0.1, "H3": 0.5}


def generate(seed: int, per_class: int) -> list[Hostile]:
    """The run's inputs: `per_class` of each class (fewer of the costly ones), shuffled."""
    rng = random.Random(seed)
    inputs = []
    for name, make in CLASSES.items():
        stream = make(random.Random(rng.randrange(2**32)))
        inputs += [next(stream) for _ in range(max(1, round(per_class * SHARE.get(name, 1.0))))]
    rng.shuffle(inputs)
    return inputs


def memory_of(pid: int) -> tuple[int, int]:
    """(resident, peak resident) bytes of a process (Linux)."""
    fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines())
    return int(fields["VmRSS"].split()[0]) * 1024, int(fields["VmHWM"].split()[0]) * 1024


class HealthProbe:
    """Polls /healthz every `interval_s` on its own connection; keeps every latency (seconds, inf for a
    failure or a timeout of `timeout_s`)."""

    def __init__(self, url: str, interval_s: float = 0.02, timeout_s: float = 5.0) -> None:
        self.url, self.interval_s, self.timeout_s = url, interval_s, timeout_s
        self.latencies: list[tuple[float, float]] = []  # (start, latency)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="healthz-probe", daemon=True)

    def _run(self) -> None:
        with httpx.Client(base_url=self.url, timeout=self.timeout_s) as client:
            while not self._stop.is_set():
                start = time.perf_counter()
                try:
                    ok = client.get("/healthz").status_code == 200
                except httpx.HTTPError:
                    ok = False
                self.latencies.append((start, time.perf_counter() - start if ok else float("inf")))
                self._stop.wait(self.interval_s)

    def __enter__(self) -> HealthProbe:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def between(self, start: float, stop: float) -> list[float]:
        return [latency for at, latency in self.latencies if start <= at <= stop]


@dataclass
class Results:
    answers: dict[str, Counter] = field(default_factory=lambda: defaultdict(Counter))
    server_errors: list[tuple[str, int, str]] = field(default_factory=list)
    changed_by_reject: list[str] = field(default_factory=list)
    worst_growth: tuple[int, str] = (0, "")
    memory: dict[str, int] = field(default_factory=dict)
    inputs: int = 0


def fingerprint(client: httpx.Client, sid: str) -> str:
    grid = client.get(f"/v1/sessions/{sid}/belief", params={"format": "grid", "layers": "true"})
    return grid.headers.get("etag", "") + hashlib.sha256(grid.content).hexdigest()


def watched_session(client: httpx.Client) -> str:
    """The session every hostile batch aims at: a belief with an utterance and an observation in it."""
    body = {
        "robot_id": "watched",
        "scene_graph": scene(),
        "target_label": "backpack",
        "label_map": {"0": "floor", "1": "backpack"},
        "grid": {"voxel_size": 0.25},
    }
    sid = client.post("/v1/sessions", json=body).raise_for_status().json()["id"]
    client.post(f"/v1/sessions/{sid}/utterances", json={"utterance": "the backpack is on the table"})
    client.post(f"/v1/sessions/{sid}/observations", json={"voxels": [[2, 2, 2]], "labels": [1]})
    return sid


def send(client: httpx.Client, hostile: Hostile, sid: str) -> httpx.Response:
    path = hostile.path.replace("{sid}", sid)
    return client.request(hostile.method, path, content=hostile.body, headers=hostile.headers)


def run(url: str, pid: int, inputs: list[Hostile]) -> Results:
    """Send every input in turn, check the watched belief after each reject aimed at it, follow a session a
    hostile creation made (poll its belief as a dashboard would, then delete it), and track memory."""
    results = Results(inputs=len(inputs))
    with httpx.Client(base_url=url, timeout=120.0) as client:
        sid = watched_session(client)
        before = fingerprint(client, sid)
        results.memory["rss_before"], results.memory["peak_before"] = memory_of(pid)
        for hostile in inputs:
            rss_before = memory_of(pid)[0]
            response = send(client, hostile, sid)
            results.answers[hostile.kind][response.status_code] += 1
            if response.status_code >= 500:
                results.server_errors.append((hostile.kind, response.status_code, response.text[:200]))
            if hostile.method == "POST" and hostile.path == "/v1/sessions" and response.status_code == 201:
                created = response.json()["id"]
                poll = client.get(f"/v1/sessions/{created}/belief")
                results.answers[hostile.kind + " (its belief polled)"][poll.status_code] += 1
                client.delete(f"/v1/sessions/{created}")
            growth = memory_of(pid)[0] - rss_before
            if len(hostile.body) <= 2**20 and growth > results.worst_growth[0]:
                results.worst_growth = (growth, hostile.kind)
            if hostile.watched:
                now = fingerprint(client, sid)
                if response.status_code >= 400 and now != before:
                    results.changed_by_reject.append(f"{hostile.kind}: {response.status_code}")
                before = now
        results.memory["rss_after"], results.memory["peak_after"] = memory_of(pid)
    return results


def heavy(seed: int) -> dict[str, Hostile]:
    """The heaviest requests a client may send within the body limits (16 MiB, 2 MiB of JSON), for /healthz
    while each runs."""
    rng = random.Random(seed)
    n = 600_000
    names = ["x" * 256] + ["floor"] * (n - 1)
    label_bomb = msgpack.packb({"voxels": packed(np.ones((n, 3), np.int32)), "labels": names})
    bad = _json({"scene_graph": {"objects": [], "regions": [1] * 1_000_000}, "utterance": "x"})
    points = _json({"scene_graph": scene(), "utterance": "x", "query_points": [[1.5, 2.5, 3.5]] * 120_000})
    deep = b"[" * 1_000_000 + b"]" * 1_000_000
    observe = "/v1/sessions/{sid}/observations"
    return {
        "H1 label bomb (600k labels, 11 MB msgpack)": Hostile("H1", "POST", observe, label_bomb, MSGPACK),
        "H2 bad list (1M items, 2 MB JSON)": Hostile("H2", "POST", "/v1/ground", bad, JSON),
        "query points (120k, 2 MB JSON)": Hostile("H2", "POST", "/v1/ground", points, JSON),
        "deep JSON (2 MB)": Hostile("deep", "POST", "/v1/scene-graphs/normalize", deep, JSON),
        "binary decode": next(binaries(rng)),
    }


def healthz_while(url: str, sid: str, hostile: Hostile, probe: HealthProbe) -> tuple[int, list[float]]:
    """(status of `hostile`, /healthz latencies measured while it was in flight)."""
    with httpx.Client(base_url=url, timeout=120.0) as client:
        start = time.perf_counter()
        status = send(client, hostile, sid).status_code
        stop = time.perf_counter()
    return status, probe.between(start, stop)


def pctl(samples: list[float]) -> str:
    if not samples:
        return "no samples"
    ms = np.asarray(samples) * 1000
    p50, p99 = np.percentile(ms, [50, 99])
    return f"p50 {p50:.1f} ms, p99 {p99:.1f} ms, max {ms.max():.1f} ms (n={len(ms)})"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--per-class", type=int, default=120, help="inputs per class (fewer binaries, places)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=None, help="write the figures here too")
    args = parser.parse_args(argv)
    inputs = generate(args.seed, args.per_class)
    proc, url = start_service(SERVICE_ENV)
    try:
        wait_ready(url, proc)
        with HealthProbe(url) as probe:
            started = time.perf_counter()
            results = run(url, proc.pid, inputs)
            during_run = probe.between(started, time.perf_counter())
            with httpx.Client(base_url=url, timeout=30.0) as client:
                sid = watched_session(client)
            during_heavy = {name: healthz_while(url, sid, h, probe) for name, h in heavy(args.seed).items()}
            peak_after_heavy = memory_of(proc.pid)[1]
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    mib = 2**20
    print(f"{results.inputs} hostile inputs, {sum(len(c) for c in results.answers.values())} answer kinds")
    for kind, counts in sorted(results.answers.items()):
        print(f"  {kind:34s} " + ", ".join(f"{status}: {n}" for status, n in sorted(counts.items())))
    changed = len(results.changed_by_reject)
    print(f"5xx answers: {len(results.server_errors)}   beliefs changed by a reject: {changed}")
    m = results.memory
    print(
        f"service RSS: {m['rss_before'] / mib:.0f} MiB before, {m['rss_after'] / mib:.0f} MiB after; peak "
        f"{m['peak_before'] / mib:.0f} -> {m['peak_after'] / mib:.0f} MiB; largest growth after one request "
        f"of <= 1 MB: {results.worst_growth[0] / mib:.1f} MiB ({results.worst_growth[1] or '-'})"
    )
    print(f"/healthz during the run: {pctl(during_run)}")
    for name, (status, latencies) in during_heavy.items():
        print(f"/healthz while {name} ({status}): {pctl(latencies)}")
    print(f"peak RSS after the heavy requests (up to 16 MB each): {peak_after_heavy / mib:.0f} MiB")
    figures = {
        "inputs": results.inputs,
        "answers": {kind: dict(counts) for kind, counts in results.answers.items()},
        "server_errors": results.server_errors,
        "changed_by_reject": results.changed_by_reject,
        "memory": m,
        "worst_growth": results.worst_growth,
        "healthz_run_ms": [1000 * x for x in during_run],
        "healthz_heavy": {
            name: {"status": s, "ms": [1000 * x for x in lat]} for name, (s, lat) in during_heavy.items()
        },
    }
    if args.json is not None:
        args.json.write_text(json.dumps(figures, indent=1, default=str))
    return figures


if __name__ == "__main__":
    main()
