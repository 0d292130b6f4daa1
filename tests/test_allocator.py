"""The glibc allocator tuning applied by every `vlmap` command."""

from __future__ import annotations

import ctypes
import ctypes.util
import platform
from typing import Any

import pytest

from app.allocator import MMAP_THRESHOLD_BYTES, TRIM_THRESHOLD_BYTES, keep_freed_buffers

glibc = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")


class MallInfo2(ctypes.Structure):
    """glibc's `struct mallinfo2` (2.33+): the allocator's own accounting, in bytes."""

    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena",
            "ordblks",
            "smblks",
            "hblks",
            "hblkhd",  # bytes in mmap-ed chunks
            "usmblks",
            "fsmblks",
            "uordblks",
            "fordblks",  # free bytes kept in the heap
            "keepcost",
        )
    ]


def _libc() -> Any:
    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    if not hasattr(libc, "mallinfo2"):
        pytest.skip("glibc before 2.33 has no mallinfo2")
    libc.mallinfo2.restype = MallInfo2
    libc.malloc.restype = ctypes.c_void_p
    libc.malloc.argtypes = [ctypes.c_size_t]
    libc.free.argtypes = [ctypes.c_void_p]
    return libc


@glibc
def test_buffers_below_the_threshold_come_from_the_heap_and_stay_there_when_freed() -> None:
    """48 MiB is above glibc's largest dynamic mmap threshold (32 MiB): by default it gets its own mapping
    and is unmapped on free. With the tuning it comes from the heap, and freeing it keeps it there."""
    assert keep_freed_buffers() is True
    libc = _libc()
    size = 48 << 20
    assert size < MMAP_THRESHOLD_BYTES
    mapped_before = libc.mallinfo2().hblkhd
    buffer = libc.malloc(size)
    assert buffer
    try:
        assert libc.mallinfo2().hblkhd == mapped_before  # not a fresh mapping
        free_before = libc.mallinfo2().fordblks
    finally:
        libc.free(buffer)
    assert libc.mallinfo2().fordblks - free_before >= size  # freed, not returned to the kernel

    whole_grid = libc.malloc(MMAP_THRESHOLD_BYTES + (32 << 20))  # above the threshold: still its own mapping
    assert whole_grid
    try:
        assert libc.mallinfo2().hblkhd - mapped_before >= MMAP_THRESHOLD_BYTES + (32 << 20)
    finally:
        libc.free(whole_grid)


def test_no_libc_found_is_reported_not_raised(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None)
    assert keep_freed_buffers() is False


class _FakeLibc:
    def __init__(self, answer: int) -> None:
        self.answer = answer
        self.calls: list[tuple[int, int]] = []

    def gnu_get_libc_version(self) -> bytes:
        return b"2.36"

    def mallopt(self, param: int, value: int) -> int:
        self.calls.append((param, value))
        return self.answer


@pytest.mark.parametrize("answer", [1, 0])
def test_both_thresholds_are_set_and_a_refusal_stops_there(
    monkeypatch: pytest.MonkeyPatch, answer: int
) -> None:
    fake = _FakeLibc(answer)
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: "libc.so.6")
    monkeypatch.setattr(ctypes, "CDLL", lambda name: fake)
    assert keep_freed_buffers() is bool(answer)
    mmap_call = (-3, MMAP_THRESHOLD_BYTES)  # <malloc.h>: M_MMAP_THRESHOLD -3, M_TRIM_THRESHOLD -1
    trim_call = (-1, TRIM_THRESHOLD_BYTES)
    assert fake.calls == ([mmap_call, trim_call] if answer else [mmap_call])


def test_a_libc_without_mallopt_is_left_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: "libc.so")
    monkeypatch.setattr(ctypes, "CDLL", lambda name: object())  # musl and others: no mallopt
    assert keep_freed_buffers() is False
