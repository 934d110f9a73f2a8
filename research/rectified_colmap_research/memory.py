"""Process memory settings for benchmarks (research only: the extractor never changes them)."""

from __future__ import annotations


def retain_freed_memory() -> bool:
    """Make this process keep the memory it frees for reuse instead of returning it to the
    system (glibc: no mmap for large blocks, no heap trimming). Returns False where this is
    not glibc (nothing changed).

    Every new pycolmap extractor, and every image of a new size, allocates a fresh scale
    space (~450 MB at 1536x1024); glibc maps such blocks anew and unmaps them when freed, so
    the kernel faults in and zeroes every page again: ~0.1-0.5 s of system time per image
    and patch. With this, the pages are reused: resident memory stays at the process's peak
    instead of falling back between images (the peak itself does not change). Process-wide
    and irreversible: meant for extraction workers, not for library imports."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, 2**31 - 1))
