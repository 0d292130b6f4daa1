"""All service settings in one place: environment variables prefixed `VLMAP_` (or a `.env` file)."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from app.belief.grid import DEFAULT_MAX_VOXELS
from app.scene_graph.model import MAX_OBJECTS_CEILING, MAX_REGIONS_CEILING
from app.stores.base import DEFAULT_IDEMPOTENCY_KEYS, DEFAULT_IDEMPOTENCY_WINDOW_S, DEFAULT_TTL_S
from app.stores.events import DEFAULT_HISTORY as DEFAULT_EVENT_HISTORY
from app.stores.recording import DEFAULT_RECORDING_FRAMES, DEFAULT_RECORDING_INTERVAL_S
from app.stores.redis_store import DEFAULT_MIRROR_BYTES

REPO_ROOT = Path(__file__).resolve().parent.parent


#: The most `max_utterance_chars` may be: the request schemas refuse a longer utterance before reading it.
MAX_UTTERANCE_CHARS_CEILING = 100_000


class Settings(BaseSettings):
    """Embedded defaults run the whole service on one machine with no external server. Where a setting is
    a default of the code it configures, that default is named once, there, and used here."""

    model_config = SettingsConfigDict(env_prefix="VLMAP_", env_file=".env", extra="ignore")

    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=1, le=65535)

    grounder: Literal["lsm", "geometric", "fixed"] = Field(
        default="lsm", description="Default spatial grounder (the shipped LSM); requests may pick others."
    )
    proposer: Literal["builtin", "lexical"] = Field(
        default="builtin",
        description="Default proposer: calibrated built-in (MiniLM features) or lexical (uniform weights).",
    )
    grounders: list[Literal["lsm", "geometric", "fixed"]] = Field(
        default=["geometric", "fixed"], description="Grounders to load besides the default one."
    )
    llm_url: str | None = Field(
        default=None,
        description="OpenAI-compatible endpoint (ending before /chat/completions) for the LLM parts.",
    )
    llm_model: str = Field(default="gpt-4o-mini", description="Model name sent to the LLM endpoint.")
    llm_api_key: str | None = Field(default=None, description="Bearer key for the LLM endpoint.")
    llm_timeout_s: float = Field(default=20.0, gt=0, description="Per-attempt timeout of LLM calls.")
    model_dir: Path = Field(default=REPO_ROOT / "models", description="Where shipped weights live.")

    max_body_bytes: int = Field(
        default=16 * 2**20, ge=1024, description="Largest request body accepted (413 above)."
    )
    max_json_body_bytes: int = Field(
        default=2 * 2**20,
        ge=1024,
        description="Largest JSON body accepted (413 above): validating JSON holds the interpreter lock, "
        "about 0.1 s per MB of small items; large observation batches go as msgpack.",
    )
    max_objects: int = Field(
        default=2000,
        ge=1,
        le=MAX_OBJECTS_CEILING,
        description="Objects allowed in one scene graph (422 above).",
    )
    max_hypotheses: int = Field(
        default=5, ge=1, le=5, description="Readings the LLM and lexical proposers keep per utterance."
    )
    max_grounded_hypotheses: int = Field(
        default=8,
        ge=1,
        le=64,
        description="Hypotheses the grounder places one by one per utterance; the others keep their mass, "
        "merged per region into one broad Gaussian each.",
    )
    max_query_points: int = Field(default=10_000, ge=0, description="query_points allowed per /v1/ground.")
    max_utterance_chars: int = Field(
        default=1000,
        ge=1,
        le=MAX_UTTERANCE_CHARS_CEILING,
        description="Characters of an utterance (/v1/ground, a session's utterances; 422 above).",
    )

    store: str = Field(
        default="memory", description='Session store: "memory" (durable in data_dir) or a redis:// URL.'
    )
    data_dir: Path | None = Field(
        default=Path("var/sessions"), description="Where the memory store logs updates (None: not durable)."
    )

    @field_validator("data_dir", mode="before")
    @classmethod
    def _empty_means_none(cls, value: object) -> object:
        # VLMAP_DATA_DIR= (empty) must mean "not durable", not the working directory.
        return None if isinstance(value, str) and not value.strip() else value

    session_ttl_s: float = Field(
        default=DEFAULT_TTL_S, gt=0, description="Sessions expire after this idle time."
    )
    store_mirror_mib: int = Field(
        default=DEFAULT_MIRROR_BYTES >> 20,
        ge=0,
        description="Redis store: MiB of session layers each process keeps as the last state it read or "
        "wrote, so the replica that wrote last updates and summarises without reading them back (0: none).",
    )
    summary_watch_s: float = Field(
        default=30.0,
        ge=0,
        description="A session whose belief was read within this many seconds gets each new version "
        "summarised in the background, ready for the next poll (0: summarise only when asked).",
    )
    recording_frames: int = Field(
        default=DEFAULT_RECORDING_FRAMES,
        ge=0,
        description="Frames each session's recording keeps (`GET .../recording.mcap`): one per belief "
        "version, about 6 kB each (the summary and its 100 top voxels), older ones thinned to every second "
        "past the limit (app.sessions.recording); 0: no recording, and no cost per update.",
    )
    recording_interval_s: float = Field(
        default=DEFAULT_RECORDING_INTERVAL_S,
        ge=0,
        description="A batch sent with summary=false is recorded off the request path, at most one frame per "
        "session this often: the latest version when it is due, so a robot streaming at camera rate costs "
        "one summary a second, not one per batch (0: a frame per version).",
    )
    events_heartbeat_s: float = Field(
        default=10.0,
        gt=0,
        description="An event stream sends a comment line after this many seconds without an event, so that "
        "proxies keep it open and a client can tell a quiet stream from a dead one; a session stream checks "
        "then that its session still exists.",
    )
    events_buffer: int = Field(
        default=256,
        ge=1,
        description="Events one stream may hold that its client has not read; one more and the stream is cut "
        "(the client resumes with Last-Event-ID): a client that does not read costs this much, and slows no "
        "writer and no other stream.",
    )
    events_history: int = Field(
        default=DEFAULT_EVENT_HISTORY,
        ge=1,
        description="Events each session keeps (at least) for a stream resumed with Last-Event-ID; an older "
        "id gets a `sync` event, telling the client to read the summary again. On Redis, in the session's "
        "stream (about 400 bytes an event; Redis may keep up to 100 more).",
    )
    events_fleet_history: int = Field(
        default=4096,
        ge=1,
        description="Events each process keeps, of every session, for fleet streams (/v1/events) resumed "
        "with Last-Event-ID.",
    )
    events_max_stream_s: float = Field(
        default=600.0,
        gt=0,
        description="An event stream ends after this long (the client resumes with Last-Event-ID): streams "
        "spread over new replicas, and a key's access is checked again.",
    )
    max_event_streams: int = Field(
        default=256,
        ge=1,
        description="Event streams one process serves at once (429 above): each holds a connection of "
        "max_connections, which robots' requests need too.",
    )
    max_sessions_per_robot: int = Field(default=16, ge=1, description="Live sessions per robot (429 above).")
    max_grid_voxels: int = Field(
        default=DEFAULT_MAX_VOXELS, ge=1, description="Voxels per session grid (memory guard)."
    )
    max_batch_voxels: int = Field(default=2_000_000, ge=1, description="Voxels per observation batch.")
    max_regions: int = Field(
        default=500,
        ge=1,
        le=MAX_REGIONS_CEILING,
        description="Regions allowed in one scene graph (422 above).",
    )
    max_coordinate_m: float = Field(
        default=1e5,
        gt=0,
        le=1e9,
        description="Largest |coordinate| and size (metres) of a scene graph, grid corner or query point "
        "(422 above): a map spans metres to kilometres, and squares of larger numbers overflow.",
    )
    max_place_voxels: int = Field(
        default=32_000_000,
        ge=1,
        description="Voxels of a session's places (each object's box with the 'on' margin, each region) "
        "summed over its scene graph, on its grid (422 above): every summary sums the belief over them.",
    )
    max_label_map_entries: int = Field(
        default=4096, ge=1, description="Entries of a session's label_map (422 above)."
    )
    max_validation_errors: int = Field(
        default=20,
        ge=1,
        le=1000,
        description="Validation errors listed in a 422 answer (its message says how many there were).",
    )
    max_concurrent_decodes: int = Field(
        default=1,
        ge=1,
        description="Spark-DSG binary decodes (each a child process) running at once in a process.",
    )
    decode_rate_per_s: float = Field(
        default=1.0, ge=0, description="Spark-DSG binary decodes per second per key (0: no limit)."
    )
    decode_rate_burst: float = Field(default=4.0, ge=1, description="Burst allowance of the decode rate.")
    max_concurrent_grids: int = Field(
        default=2,
        ge=1,
        description="Whole-grid belief downloads (format=grid) being encoded at once in a process.",
    )
    busy_wait_s: float = Field(
        default=2.0,
        ge=0,
        description="How long a decode or grid download waits for a free slot before a 429 with Retry-After.",
    )
    idempotency_window_s: float = Field(
        default=DEFAULT_IDEMPOTENCY_WINDOW_S,
        gt=0,
        description="How long a session remembers an Idempotency-Key and the answer it was given.",
    )
    idempotency_keys_per_session: int = Field(
        default=DEFAULT_IDEMPOTENCY_KEYS,
        ge=1,
        description="Idempotency-Keys a session remembers at most (the oldest are forgotten first).",
    )

    api_keys_file: Path | None = Field(
        default=None,
        description='JSON list of {"name", "role", "sha256", "robot_ids"} (see `vlmap keys new`).',
    )
    api_keys: str | None = Field(
        default=None, description="The same JSON list, inline (when no file is given)."
    )
    allow_open: bool = Field(
        default=False, description="Serve without keys on a non-loopback address (refused otherwise)."
    )
    rate_limit_per_s: float = Field(default=200.0, ge=0, description="Requests per second per key (0: off).")
    rate_limit_burst: float = Field(default=400.0, ge=1, description="Burst allowance of the per-key rate.")
    max_connections: int = Field(
        default=1000,
        ge=1,
        description="Open connections and requests in flight per process; beyond it new ones get a 503.",
    )
    header_timeout_s: float = Field(
        default=10.0, gt=0, description="A request's line and headers must arrive within this time."
    )
    max_header_bytes: int = Field(
        default=32 * 1024, ge=1024, description="Request line and headers, in bytes (431 above)."
    )
    body_timeout_s: float = Field(
        default=30.0, gt=0, description="A request's body must arrive within this time (408 after)."
    )
    keep_alive_s: int = Field(default=5, ge=1, description="Idle time before a keep-alive connection closes.")

    log_level: str = "INFO"
    log_json: bool = Field(default=True, description="One JSON object per log line (false: plain text).")
    torch_threads: int = Field(
        default=1, ge=1, description="Threads per LSM forward pass (requests run in parallel across workers)."
    )
    text_encoder_precision: Literal["auto", "float32", "bfloat16"] = Field(
        default="auto",
        description="MiniLM projections in bfloat16 where the CPU has native bfloat16 instructions (AMX or "
        "AVX512-BF16) and the probe embedding agrees with float32 (auto), always float32, or bfloat16 (an "
        "error without them).",
    )
    worker_threads: int = Field(default=8, ge=1, description="Threads for CPU-bound work off the event loop.")
    worker_processes: int = Field(
        default=1,
        ge=0,
        description="Worker processes that ground utterances with the local models, so that a grounding "
        "never holds the request process's interpreter lock (0: ground on the worker threads).",
    )


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings, read once from the environment."""
    return Settings()
