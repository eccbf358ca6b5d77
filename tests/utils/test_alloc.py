"""tune_allocator: large blocks stay on glibc's heap and stay mapped after free."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

from sss2bathy.utils.alloc import ENV_VAR, tune_allocator

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"

# malloc + free 64 MiB: glibc's mallinfo2 (bytes) while held and after the free, less before
_PROBE = """
import ctypes, json, sys
from sss2bathy.utils.alloc import tune_allocator
fields = ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
          "uordblks", "fordblks", "keepcost")
class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in fields]
libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = MallInfo2
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = (ctypes.c_void_p,)
applied = tune_allocator().applied if sys.argv[1] == "tuned" else None
base = libc.mallinfo2()
block = libc.malloc(64 << 20)
ctypes.memset(block, 1, 64 << 20)
held = libc.mallinfo2()
libc.free(block)
freed = libc.mallinfo2()
print(json.dumps({"applied": applied,
                  "held_mmap": held.hblkhd - base.hblkhd, "freed_mmap": freed.hblkhd - base.hblkhd,
                  "freed_heap": freed.arena - base.arena, "freed_free": freed.fordblks - base.fordblks}))
"""


def _probe(mode: str) -> dict:
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in (ENV_VAR, "LD_PRELOAD", "GLIBC_TUNABLES") and not k.startswith("MALLOC_")
    }
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, env=env, check=True
    )
    return json.loads(out.stdout)


@pytest.mark.skipif(not GLIBC, reason="glibc malloc only")
def test_large_blocks_come_from_the_heap_and_stay_mapped():
    mib64 = 64 << 20
    default = _probe("default")
    assert default["held_mmap"] >= mib64  # glibc's default: a fresh mmap ...
    assert default["freed_mmap"] == 0  # ... unmapped on free (re-faulted on the next one)
    tuned = _probe("tuned")
    assert tuned["applied"] is True
    assert tuned["held_mmap"] == 0  # served from the heap
    assert tuned["freed_heap"] >= mib64 and tuned["freed_free"] >= mib64  # kept for reuse


def test_opt_out_preload_and_arguments(monkeypatch):
    monkeypatch.setenv(ENV_VAR, "default")
    skipped = tune_allocator()
    assert not skipped.applied and ENV_VAR in skipped.reason
    monkeypatch.delenv(ENV_VAR)
    monkeypatch.setenv("LD_PRELOAD", "/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4")
    preloaded = tune_allocator()
    assert not preloaded.applied and "tcmalloc" in preloaded.reason
    with pytest.raises(ValueError, match="trim_threshold_bytes"):
        tune_allocator(trim_threshold_bytes=-1)
    with pytest.raises(ValueError, match="mmap_threshold_bytes"):
        tune_allocator(mmap_threshold_bytes=1 << 30)  # above glibc's 32 MiB cap
    with pytest.raises(ValueError, match="mmap_max"):
        tune_allocator(mmap_max=True)
