"""Keep glibc's allocator from returning (and re-faulting) the memory of large tensors.

With its defaults, glibc ``malloc`` serves every block above ``M_MMAP_THRESHOLD`` (128 KiB,
raised dynamically up to 32 MiB) with a fresh ``mmap`` and unmaps it on ``free``, and trims
the heap's top above ``M_TRIM_THRESHOLD``. A training step allocates and frees the same
multi-megabyte temporaries thousands of times, so every one of them is page-faulted in
again (zeroed by the kernel): measured here ~9 ms per 32 MiB tensor, and a fifth of a
SIREN step. :func:`tune_allocator` switches that off in-process through ``mallopt``
(no ``LD_PRELOAD`` needed): large blocks come from the heap (``M_MMAP_MAX = 0``), freed
memory stays mapped for reuse up to ``trim_threshold_bytes`` (``M_TRIM_THRESHOLD``) and the
heap grows in steps of ``top_pad_bytes`` (``M_TOP_PAD``). The cost is memory: the process
keeps its peak heap (less what exceeds the trim threshold) instead of giving it back.

Where glibc is absent (macOS, Windows, musl) or another allocator is preloaded (tcmalloc,
jemalloc: their ``mallopt`` is a stub), it does nothing and says so in a debug log. The
environment variable ``SSS2BATHY_MALLOC=default`` opts out.

Call it once, early, in an entry point (a process-wide setting: never from library code
that others import).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import platform
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

#: ``mallopt`` parameter numbers (glibc ``<malloc.h>``).
M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3
M_MMAP_MAX = -4

#: Environment variable: ``default`` leaves the allocator alone.
ENV_VAR = "SSS2BATHY_MALLOC"

#: glibc caps ``M_MMAP_THRESHOLD`` at ``HEAP_MAX_SIZE / 2`` (32 MiB on 64-bit).
MAX_MMAP_THRESHOLD = 32 * 1024 * 1024

_PRELOADED_ALLOCATORS = ("tcmalloc", "jemalloc", "mimalloc")


@dataclass(frozen=True)
class AllocatorTuning:
    """What :func:`tune_allocator` did.

    Attributes:
        applied: whether every ``mallopt`` call succeeded.
        reason: why not (empty when applied).
        settings: the ``mallopt`` parameters set, by name.
    """

    applied: bool
    reason: str = ""
    settings: dict[str, int] = field(default_factory=dict)


def _glibc() -> ctypes.CDLL | None:
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
    if not hasattr(libc, "mallopt") or not hasattr(libc, "gnu_get_libc_version"):
        return None
    libc.mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    libc.mallopt.restype = ctypes.c_int
    return libc


def _check_bytes(name: str, value: int, maximum: int = 2**31 - 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= maximum:
        raise ValueError(f"{name}: expected an integer in [0, {maximum}], found {value!r}")
    return value


def tune_allocator(
    *,
    trim_threshold_bytes: int = 1 << 30,
    top_pad_bytes: int = 64 << 20,
    mmap_max: int = 0,
    mmap_threshold_bytes: int | None = None,
) -> AllocatorTuning:
    """Set glibc ``malloc`` up for large, short-lived tensors (module docstring).

    Args:
        trim_threshold_bytes: free memory at the heap's top kept mapped (``M_TRIM_THRESHOLD``).
        top_pad_bytes: extra bytes requested whenever the heap grows (``M_TOP_PAD``).
        mmap_max: most blocks served by ``mmap`` at once (``M_MMAP_MAX``); 0 = none, every
            block comes from the heap.
        mmap_threshold_bytes: blocks at least this big use ``mmap`` while ``mmap_max`` allows
            (``M_MMAP_THRESHOLD``, at most :data:`MAX_MMAP_THRESHOLD`); ``None`` = unchanged.

    Returns:
        An :class:`AllocatorTuning`; ``applied=False`` (nothing changed) without glibc, with
        another allocator preloaded, or with ``SSS2BATHY_MALLOC=default``.
    """
    settings = {
        "M_TRIM_THRESHOLD": _check_bytes("trim_threshold_bytes", trim_threshold_bytes),
        "M_TOP_PAD": _check_bytes("top_pad_bytes", top_pad_bytes),
        "M_MMAP_MAX": _check_bytes("mmap_max", mmap_max),
    }
    if mmap_threshold_bytes is not None:
        settings["M_MMAP_THRESHOLD"] = _check_bytes(
            "mmap_threshold_bytes", mmap_threshold_bytes, MAX_MMAP_THRESHOLD
        )
    if os.environ.get(ENV_VAR, "").strip().lower() == "default":
        return _skipped(f"{ENV_VAR}=default")
    preload = os.environ.get("LD_PRELOAD", "")
    other = next((name for name in _PRELOADED_ALLOCATORS if name in preload), None)
    if other is not None:
        return _skipped(f"{other} is preloaded (LD_PRELOAD)")
    libc = _glibc()
    if libc is None:
        return _skipped(f"no glibc ({platform.system()}, {platform.libc_ver()[0] or 'unknown'})")
    params = {
        "M_TRIM_THRESHOLD": M_TRIM_THRESHOLD,
        "M_TOP_PAD": M_TOP_PAD,
        "M_MMAP_MAX": M_MMAP_MAX,
        "M_MMAP_THRESHOLD": M_MMAP_THRESHOLD,
    }
    failed = [name for name, value in settings.items() if libc.mallopt(params[name], value) != 1]
    if failed:
        return _skipped(f"mallopt refused {failed}", settings)
    log.debug("glibc malloc tuned: %s", settings)
    return AllocatorTuning(True, "", settings)


def _skipped(reason: str, settings: dict[str, int] | None = None) -> AllocatorTuning:
    log.debug("allocator left as it is: %s", reason)
    return AllocatorTuning(False, reason, dict(settings or {}))
