"""The CPU allocator setting: the right mallopt parameters, and it takes effect on this glibc machine."""

from __future__ import annotations

import sys

import pytest

from splatreplace_ns.method import cpu_allocator


class RecordingLibc:
    def __init__(self, answer: int = 1) -> None:
        self.calls, self.answer = [], answer

    def mallopt(self, param: int, value: int) -> int:
        self.calls.append((param, value))
        return self.answer


def test_sets_the_mmap_and_trim_thresholds():
    libc = RecordingLibc()
    assert cpu_allocator.keep_freed_buffers(libc) is True
    assert libc.calls == [(-3, 1 << 30), (-1, (1 << 31) - 1)]  # glibc's M_MMAP_THRESHOLD, M_TRIM_THRESHOLD


def test_a_refused_setting_is_reported():
    assert cpu_allocator.keep_freed_buffers(RecordingLibc(answer=0)) is False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_accepted_by_this_processes_glibc():
    assert cpu_allocator.keep_freed_buffers() is True
