"""The glibc allocator tuning applied by every `vlmap` command."""

from __future__ import annotations

import platform

import pytest

from app.allocator import keep_freed_buffers


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_thresholds_are_accepted_by_glibc():
    assert keep_freed_buffers() is True
