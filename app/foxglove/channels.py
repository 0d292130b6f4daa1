"""One session's channels (the topics of `app.foxglove`) in a Foxglove SDK context: what the live server and
the MCAP writer log the converted messages on."""

from __future__ import annotations

import json
from typing import Any

import foxglove
from foxglove.channels import LogChannel, PointCloudChannel, SceneUpdateChannel

from app.foxglove.messages import Message, Topics

#: The JSON topic's schema: the summary of `GET /v1/sessions/{id}/belief` with its version.
SUMMARY_SCHEMA = foxglove.Schema(
    name="vlmap.BeliefSummary",
    encoding="jsonschema",
    data=json.dumps(
        {
            "title": "vlmap.BeliefSummary",
            "description": "PosteriorSummaryOut of the VL-Map OpenAPI, with `version` and `target_label`.",
            "type": "object",
            "properties": {"version": {"type": "integer"}, "target_label": {"type": ["string", "null"]}},
        }
    ).encode(),
)


class SessionChannels:
    """The channels of one session's topics in `context`."""

    def __init__(self, topics: Topics, context: foxglove.Context) -> None:
        self.topics = topics
        self._channels: dict[str, Any] = {
            topics.scene_graph: SceneUpdateChannel(topics.scene_graph, context=context),
            topics.belief: PointCloudChannel(topics.belief, context=context),
            topics.estimate: SceneUpdateChannel(topics.estimate, context=context),
            topics.summary: foxglove.Channel(
                topics.summary, schema=SUMMARY_SCHEMA, message_encoding="json", context=context
            ),
            topics.mixture: SceneUpdateChannel(topics.mixture, context=context),
            topics.utterances: LogChannel(topics.utterances, context=context),
        }

    def log(self, topic: str, message: Message, log_time_ns: int) -> None:
        self._channels[topic].log(message, log_time=log_time_ns)

    def close(self) -> None:
        for channel in self._channels.values():
            channel.close()
