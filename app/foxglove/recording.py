"""A session's recording frames as an MCAP file (`GET /v1/sessions/{id}/recording.mcap`), written by the
Foxglove SDK with the topics and schemas of the live view (`app.foxglove`)."""

from __future__ import annotations

import io
from collections.abc import Iterable
from typing import Any

import foxglove
from foxglove.mcap import MCAPWriteOptions

from app.foxglove.channels import SessionChannels
from app.foxglove.messages import Converter, Topics


def mcap_bytes(session_id: str, voxel_size: float, frames: Iterable[dict[str, Any]]) -> bytes:
    """The frames (`Frame.to_json`, oldest first) as MCAP; log times in ns, never going back (a frame's
    time is its version's commit on the store's clock, an unfused utterance's when it was recorded)."""
    context, out = foxglove.Context(), io.BytesIO()
    # One compression thread: a request's file is small, and the service's CPUs serve other requests.
    options = MCAPWriteOptions(compression_threads=0, profile="")
    writer = foxglove.open_mcap(out, context=context, writer_options=options)
    channels = SessionChannels(Topics(session_id), context)
    converter, last = Converter(Topics(session_id), voxel_size), 0
    try:
        for frame in frames:
            last = max(last, round(float(frame["at"]) * 1e9))
            for topic, message in converter.messages(frame):
                channels.log(topic, message, last)
    finally:
        writer.close()
        channels.close()
    return out.getvalue()
