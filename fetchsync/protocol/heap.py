"""Keeping glibc from holding a process's freed large buffers for good.

Both ends use it: the watch agent on the laptop and the endpoint on the robot
(Python 3.6, the standard library only).
"""

from typing import Any, Dict

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters
M_MMAP_THRESHOLD = -3
# Buffers from 2 MiB get mappings of their own, unmapped when freed; smaller ones (the
# 1 MiB file reads and batches) stay in the heaps, whose free top is trimmed beyond 4 MiB.
MMAP_FROM = 2 * 2**20
TRIM_FROM = 4 * 2**20

_LIBC: Dict[str, Any] = {}


def libc(name: str) -> Any:
    """The C library's function ``name`` if the process has glibc's, else None."""
    if name not in _LIBC:
        import ctypes  # here: ~4 ms, paid only by the processes that call this

        try:
            # the symbols the process has loaded: glibc's, on a glibc system
            _LIBC[name] = getattr(ctypes.CDLL(None), name, None)
        except (OSError, AttributeError):
            _LIBC[name] = None
    return _LIBC[name]


def map_large_buffers() -> None:
    """Fix glibc's mmap and trim thresholds, so freed large buffers go back.

    glibc raises its mmap threshold to the size of each large buffer freed (up
    to 32 MiB) and its trim threshold to twice that. From then on such buffers
    come from the heaps, and what is freed stays at their top: ``malloc_trim``
    reaches only the main heap's, and only when asked. Fixing both thresholds
    keeps what a heap holds free to 4 MiB. After a first sync of 7,000 files /
    150 MiB (bench/watch.py's idle case, loopback): the agent 122 -> 70 MiB
    resident (23 MiB of live Python objects), the robot's endpoint 87 -> 37 MiB
    (the local robot, 27 Nov). Not lower: with every buffer of 256 KiB or more
    mapped, each file's 1 MiB read buffer cost an mmap and its page faults, and
    a 500-file burst took 3.5x the CPU (131 -> 497 ms, local robot).
    """
    mallopt = libc("mallopt")
    if mallopt is not None:
        mallopt(M_MMAP_THRESHOLD, MMAP_FROM)
        mallopt(M_TRIM_THRESHOLD, TRIM_FROM)
