"""The binary wire format of observation batches and belief grids (msgpack with raw little-endian arrays).

An observation batch is a msgpack map:

    {"stamp": float | nil,
     "voxels":   {"dtype": "<i4", "shape": [N, 3], "data": <bytes>}   # voxel indices i, j, k  -- or --
     "points":   {"dtype": "<f4", "shape": [N, 3], "data": <bytes>},  # points in metres (or "<f8")
     "labels":   {"dtype": "<u4", "shape": [N],    "data": <bytes>}   # label-map ids  -- or --
                 ["backpack", "chair", ...],                            # class names  -- or --
     "p_target": {"dtype": "<f4", "shape": [N],    "data": <bytes>},  # detector probabilities
     "sensor_model": {"tp": float, "fp": float} | nil}

It means exactly what the JSON batch (`ObservationBatchJson`) means; both decode into `ObservationBatch`.
A belief grid (GET .../belief?format=grid) uses the same array encoding.
"""

from __future__ import annotations

import math
import struct
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from functools import partial
from typing import Any

import msgpack
import numpy as np
from fastapi import Request
from fastapi.responses import StreamingResponse
from pydantic import TypeAdapter

from app.api.bodies import is_json, json_bytes, media_type, validate_json
from app.api.schemas import MAX_LABEL_CHARS, ObservationBatchJson
from app.belief.session import LabelNames, Session
from app.errors import InvalidInput, LimitExceeded, UnsupportedMediaType
from app.sessions.batch import ObservationBatch

#: Runs a function on a worker thread: `run(func, *args)`.
Runner = Callable[..., Awaitable[Any]]

MSGPACK_TYPES = ("application/msgpack", "application/x-msgpack", "application/vnd.msgpack")

_ALLOWED_DTYPES = {
    "voxels": ("<i4", "<i8"),
    "points": ("<f4", "<f8"),
    "labels": ("<u4", "<i4", "<u2", "<u1", "|u1"),  # numpy spells uint8 "|u1" (no byte order)
    "p_target": ("<f4", "<f8"),
}


def unpack_array(packed: Any, field: str, max_rows: int) -> np.ndarray:
    """The array a {dtype, shape, data} map describes, checked against the dtypes allowed for `field` and a
    first dimension of at most `max_rows` (so that no size arithmetic can overflow)."""
    if not isinstance(packed, dict) or set(packed) != {"dtype", "shape", "data"}:
        msg = "must be a map with exactly dtype, shape and data"
        raise InvalidInput(msg, field=field)
    dtype, shape, data = packed["dtype"], packed["shape"], packed["data"]
    allowed = _ALLOWED_DTYPES[field]
    if dtype not in allowed:
        msg = f"dtype {dtype!r} is not one of {list(allowed)}"
        raise InvalidInput(msg, field=f"{field}.dtype")
    want_dims = 2 if field in ("voxels", "points") else 1
    if (
        not isinstance(shape, list)
        or len(shape) != want_dims
        or not all(type(s) is int and s >= 0 for s in shape)  # bool is an int to isinstance
        or (want_dims == 2 and shape[1] != 3)
    ):
        msg = f"shape must be {'[N, 3]' if want_dims == 2 else '[N]'}, got {str(shape)[:60]}"
        raise InvalidInput(msg, field=f"{field}.shape")
    check_batch_size(shape[0], max_rows)
    if not isinstance(data, bytes):
        msg = "data must be raw bytes (msgpack bin)"
        raise InvalidInput(msg, field=f"{field}.data")
    expected = np.dtype(dtype).itemsize * math.prod(shape)
    if len(data) != expected:
        msg = f"{len(data)} bytes do not hold shape {shape} of {dtype} ({expected} bytes)"
        raise InvalidInput(msg, field=f"{field}.data")
    return np.frombuffer(data, dtype=np.dtype(dtype)).reshape(shape)


def decode_label_names(labels: list[Any], max_rows: int) -> LabelNames:
    """A list of class names as `LabelNames`; every name a string of at most `MAX_LABEL_CHARS`."""
    check_batch_size(len(labels), max_rows)
    for index, name in enumerate(labels):
        if not isinstance(name, str):
            msg = "a label list must hold class names (strings); send ids as a packed array"
            raise InvalidInput(msg, field=f"labels.{index}")
        if len(name) > MAX_LABEL_CHARS:
            msg = f"a class name has at most {MAX_LABEL_CHARS} characters, got {len(name)}"
            raise InvalidInput(msg, field=f"labels.{index}")
    return LabelNames.of(labels)


def decode_msgpack_batch(body: bytes, max_voxels: int) -> ObservationBatch:
    """Decode and validate a msgpack observation batch (see the module docstring)."""
    try:
        # The unpacker's own limits refuse what no valid batch holds before building it: a label longer
        # than MAX_LABEL_CHARS (4 bytes a character in UTF-8), more labels than a batch, a map of more than
        # its keys.
        envelope = msgpack.unpackb(
            body,
            raw=False,
            strict_map_key=True,
            max_bin_len=len(body),
            max_str_len=4 * MAX_LABEL_CHARS,
            max_array_len=max(max_voxels, 3),
            max_map_len=8,
            max_ext_len=0,
        )
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError, TypeError) as exc:
        msg = f"body is not a msgpack batch within its limits: {str(exc)[:200]}"
        raise InvalidInput(msg, field="body") from exc
    if not isinstance(envelope, dict):
        msg = "body must be a msgpack map"
        raise InvalidInput(msg, field="body")
    unknown = set(envelope) - {"stamp", "voxels", "points", "labels", "p_target", "sensor_model"}
    if unknown:
        msg = f"unknown keys {sorted(str(k)[:40] for k in unknown)[:10]}"
        raise InvalidInput(msg, field="body")
    stamp = envelope.get("stamp")
    if stamp is not None and not (
        isinstance(stamp, int | float) and not isinstance(stamp, bool) and math.isfinite(stamp)
    ):
        msg = "stamp must be a finite number"
        raise InvalidInput(msg, field="stamp")
    arrays: dict[str, np.ndarray | None] = {}
    for name in ("voxels", "points", "p_target"):
        packed = envelope.get(name)
        arrays[name] = unpack_array(packed, name, max_voxels) if packed is not None else None
    labels_raw = envelope.get("labels")
    labels: np.ndarray | LabelNames | None
    if labels_raw is None:
        labels = None
    elif isinstance(labels_raw, list):
        labels = decode_label_names(labels_raw, max_voxels)
    else:
        labels = unpack_array(labels_raw, "labels", max_voxels).astype(np.int64)
    sensor = envelope.get("sensor_model")
    sensor = {} if sensor is None else sensor  # nil is absent; false or 0 is no map (as JSON's schema says)
    if not isinstance(sensor, dict) or set(sensor) - {"tp", "fp"}:
        msg = "sensor_model must be a map with tp and/or fp"
        raise InvalidInput(msg, field="sensor_model")
    return ObservationBatch(
        stamp=float(stamp) if stamp is not None else None,
        voxels=arrays["voxels"].astype(np.int64) if arrays["voxels"] is not None else None,
        points=arrays["points"].astype(np.float64) if arrays["points"] is not None else None,
        labels=labels,
        p_target=arrays["p_target"].astype(np.float64) if arrays["p_target"] is not None else None,
        tp=_rate(sensor.get("tp"), "tp"),
        fp=_rate(sensor.get("fp"), "fp"),
    )


def _rate(value: Any, name: str) -> float | None:
    if value is None:
        return None
    if not isinstance(value, int | float) or isinstance(value, bool):
        msg = "must be a number"
        raise InvalidInput(msg, field=f"sensor_model.{name}")
    try:
        return float(value)
    except OverflowError as exc:  # an integer beyond float's range
        msg = "must be a number between 0 and 1"
        raise InvalidInput(msg, field=f"sensor_model.{name}") from exc


def check_batch_size(n: int, max_voxels: int) -> None:
    if n > max_voxels:
        msg = f"a batch may carry at most {max_voxels} voxels, got {n}"
        raise LimitExceeded(msg, limit_name="max_batch_voxels")


#: Voxels per chunk of the grid encoder's passes and of the stream it writes (1 MiB of float32).
_GRID_CHUNK = 1 << 18


def belief_grid_stream(
    session_id: str, version: int, grid: dict[str, Any], lang: np.ndarray, vis: np.ndarray, layers: bool
) -> tuple[int, Iterator[bytes]]:
    """(length, chunks) of the msgpack of GET .../belief?format=grid: {session_id, version, grid, posterior[,
    lang, vis]}, each array as `pack_array` writes it. The posterior is computed a chunk at a time as the
    chunks are taken, so that a download holds its copy of the layers and one chunk, not whole encoded arrays
    (a 16M-voxel grid took ~450 MB per download when packed whole)."""
    n = len(lang)
    names = ("posterior", "lang", "vis") if layers else ("posterior",)
    head = msgpack.packb({"session_id": session_id, "version": version, "grid": grid}, use_bin_type=True)
    # A map's header counts its entries: the arrays follow the three entries packed above as more of them.
    head = bytes([0x80 | (3 + len(names))]) + head[1:]
    metas = {}
    for name in names:
        meta = msgpack.packb(name, use_bin_type=True) + b"\x83"  # {dtype, shape, data}
        meta += msgpack.packb("dtype") + msgpack.packb("<f4") + msgpack.packb("shape") + msgpack.packb([n])
        metas[name] = meta + msgpack.packb("data") + b"\xc6" + struct.pack(">I", 4 * n)  # bin 32 header
    length = len(head) + sum(len(meta) + 4 * n for meta in metas.values())

    def sums(start: int) -> np.ndarray:
        stop = start + _GRID_CHUNK
        total: np.ndarray = lang[start:stop].astype(np.float64) + vis[start:stop]
        return total

    def chunks() -> Iterator[bytes]:
        yield head
        for name, meta in metas.items():
            yield meta
            if name == "posterior":
                peak = max(float(sums(start).max()) for start in range(0, n, _GRID_CHUNK))
                total = sum(float(np.exp(sums(start) - peak).sum()) for start in range(0, n, _GRID_CHUNK))
                for start in range(0, n, _GRID_CHUNK):
                    yield (np.exp(sums(start) - peak) / total).astype("<f4").tobytes()
            else:
                layer = lang if name == "lang" else vis
                for start in range(0, n, _GRID_CHUNK):
                    yield layer[start : start + _GRID_CHUNK].astype("<f4", copy=False).tobytes()

    return length, chunks()


def _packed(field: str) -> dict[str, object]:
    """A PackedArray of the dtypes `field` allows (`unpack_array`), as an OpenAPI schema."""
    return {
        "allOf": [
            {"$ref": "#/components/schemas/PackedArray"},
            {"properties": {"dtype": {"enum": list(_ALLOWED_DTYPES[field])}}},
        ]
    }


#: The OpenAPI request body of POST /v1/sessions/{id}/observations: the JSON batch, or the same as msgpack.
OBSERVATION_REQUEST_BODY = {
    "required": True,
    "content": {
        "application/json": {"schema": {"$ref": "#/components/schemas/ObservationBatchJson"}},
        "application/msgpack": {
            "schema": {
                "type": "object",
                "description": "The same batch as msgpack with raw little-endian arrays (app/api/wire.py).",
                "additionalProperties": False,
                "properties": {
                    "stamp": {"type": "number"},
                    "voxels": _packed("voxels"),
                    "points": _packed("points"),
                    "labels": {"oneOf": [_packed("labels"), {"type": "array", "items": {"type": "string"}}]},
                    "p_target": _packed("p_target"),
                    "sensor_model": {"$ref": "#/components/schemas/SensorModelOverride"},
                },
            }
        },
    },
}

#: The OpenAPI responses of GET /v1/sessions/{id}/belief besides its errors: the summary or the grid.
BELIEF_RESPONSES: dict[int | str, dict[str, object]] = {
    200: {
        "description": "The posterior summary (JSON), or with format=grid the whole posterior (msgpack).",
        "content": {"application/msgpack": {"schema": {"type": "string", "format": "binary"}}},
        "headers": {"ETag": {"description": "The belief version.", "schema": {"type": "string"}}},
    },
    304: {"description": "Not modified since the ETag given in If-None-Match."},
}

_JSON_BATCH = TypeAdapter(ObservationBatchJson)


def decode_json_batch(raw: bytes, max_voxels: int, max_errors: int) -> ObservationBatch:
    """A JSON batch (`ObservationBatchJson`), decoded as `decode_msgpack_batch` decodes its twin."""
    body = validate_json(_JSON_BATCH, raw, max_errors)
    n = len(body.voxels or body.points or [])
    check_batch_size(max(n, len(body.labels or body.p_target or [])), max_voxels)
    labels: np.ndarray | LabelNames | None = None
    if body.labels is not None:
        if body.labels and isinstance(body.labels[0], str):
            labels = LabelNames.of(body.labels)
        else:
            labels = np.asarray(body.labels, dtype=np.int64)
    return ObservationBatch(
        stamp=body.stamp,
        voxels=np.asarray(body.voxels, dtype=np.int64).reshape(-1, 3) if body.voxels is not None else None,
        points=np.asarray(body.points, dtype=np.float64).reshape(-1, 3) if body.points is not None else None,
        labels=labels,
        p_target=np.asarray(body.p_target, dtype=np.float64) if body.p_target is not None else None,
        tp=body.sensor_model.tp if body.sensor_model else None,
        fp=body.sensor_model.fp if body.sensor_model else None,
    )


#: msgpack bodies up to this size (a 16k-voxel camera view) are decoded on the event loop: a few
#: milliseconds, less than the two thread switches a worker thread would cost.
INLINE_DECODE_BYTES = 256 << 10


async def read_batch(request: Request, run: Runner, max_voxels: int, max_errors: int) -> ObservationBatch:
    """The request's observation batch, JSON or msgpack (415 otherwise); large ones decoded by `run`."""
    content_type = media_type(request)
    if content_type in MSGPACK_TYPES:
        raw = await request.body()
        decode = partial(decode_msgpack_batch, raw, max_voxels)
        return decode() if len(raw) <= INLINE_DECODE_BYTES else await run(decode)
    if is_json(content_type):  # "...+json" too, as every JSON body of the API
        body = await json_bytes(request)
        batch: ObservationBatch = await run(decode_json_batch, body, max_voxels, max_errors)
        return batch
    msg = f"unsupported content type {content_type!r}: send application/json or application/msgpack"
    raise UnsupportedMediaType(msg, field="content-type")


def belief_grid_response(
    state: Session, layers: bool, run: Runner, release: Callable[[], None]
) -> StreamingResponse:
    """The whole posterior (and layers) of `state` as a streamed msgpack answer; each chunk is made by `run`
    (a worker thread) and `release` is called after the last one is sent or the client hung up."""
    belief = state.belief
    length, chunks = belief_grid_stream(
        state.id, state.version, state.grid.to_dict(), belief.lang, belief.vis, layers
    )

    async def body() -> AsyncIterator[bytes]:
        try:
            while (chunk := await run(next, chunks, None)) is not None:
                yield chunk
        finally:
            release()

    headers = {"ETag": f'"v{state.version}"', "Content-Length": str(length)}
    return StreamingResponse(body(), media_type="application/msgpack", headers=headers)
