"""How the stores bound a session's recording (`app.sessions.recording`): `thin`, the decimation."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

#: Default frames a session's recording keeps (`Settings.recording_frames`).
DEFAULT_RECORDING_FRAMES = 256
#: Default seconds between a session's frames of batches sent without a summary
#: (`Settings.recording_interval_s`).
DEFAULT_RECORDING_INTERVAL_S = 1.0
#: First byte of a stored frame: kept by `thin` (utterances, the first frame), or a thinnable frame of level
#: 0 (as it arrived). A frame that survived `thin` l times is marked `level_marker(l)`.
KEEP, THIN = b"k", b"s"
_LEVELS = 0x80  # level l >= 1 is the byte 0x80 + l


def level_marker(level: int) -> bytes:
    """The first byte of a thinnable frame of `level`."""
    return THIN if level == 0 else bytes([_LEVELS + level])


def level(frame: bytes) -> int | None:
    """A stored frame's level; None for a frame `thin` keeps."""
    marker = frame[0] if frame else KEEP[0]
    if marker == THIN[0]:
        return 0
    return marker - _LEVELS if marker > _LEVELS else None


def thin(frames: Sequence[bytes], limit: int) -> list[bytes]:
    """The stored frames after one more arrived (`app.sessions.recording`); the Redis store's script does
    the same.

    Past `limit`, one level is halved: every second of its frames goes (the oldest stays) and the others
    move up a level. The level is the lowest holding more than its share of the limit (the limit over the
    levels present plus one), else the highest with two frames or more. Frames of level l are 2^l arrivals
    apart, and a frame's level grows with its age, so the recording spans the whole session at a
    resolution that halves with age while its recent frames stay at full rate. The first and the newest
    frames and the `KEEP` frames are never thinned; should they alone pass twice the limit, the oldest go.
    """
    out = list(frames)
    if len(out) <= limit:
        return out
    counts = Counter(lv for frame in out[1:-1] if (lv := level(frame)) is not None)
    halved = _level_to_halve(counts, limit)
    if halved is not None:
        kept, drop = out[:1], False
        for frame in out[1:-1]:
            if level(frame) != halved:
                kept.append(frame)
                continue
            if not drop:
                kept.append(level_marker(halved + 1) + frame[1:])
            drop = not drop
        out = [*kept, out[-1]]
    return out[-2 * limit :]


def _level_to_halve(counts: Counter[int], limit: int) -> int | None:
    share = max(2, limit // (len(counts) + 1))
    over = sorted(lv for lv, n in counts.items() if n > share)
    if over:
        return over[0]
    pairs = [lv for lv, n in counts.items() if n >= 2]
    return max(pairs) if pairs else None
