"""How the stores bound a session's recording (`app.sessions.recording`): `thin`, the decimation."""

from __future__ import annotations

from collections.abc import Sequence

#: Default frames a session's recording keeps (`Settings.recording_frames`).
DEFAULT_RECORDING_FRAMES = 256
#: Default seconds between a session's frames of batches sent without a summary
#: (`Settings.recording_interval_s`).
DEFAULT_RECORDING_INTERVAL_S = 1.0
#: First byte of a stored frame: kept by `thin` (utterances, the first frame), or not.
KEEP, THIN = b"k", b"s"


def thin(frames: Sequence[bytes], limit: int) -> list[bytes]:
    """The stored frames after one more arrived (`app.sessions.recording`); the Redis store's script does
    the same."""
    out = list(frames)
    if len(out) <= limit:
        return out
    half, drop, kept = len(out) // 2, False, out[:1]
    for frame in out[1:half]:
        if frame[:1] == KEEP:
            kept.append(frame)
            continue
        if not drop:
            kept.append(frame)
        drop = not drop
    return (kept + out[half:])[-2 * limit :]
