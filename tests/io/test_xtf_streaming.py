"""The XTF reader in bounded memory: parsed pings hold where their samples lie, not the
samples, and resampling a few pings at a time gives what one block gives."""

from __future__ import annotations

import numpy as np

import sss2bathy.io.xtf_packets as packets
from sss2bathy.io.xtf import read_xtf, write_xtf
from tests.io.conftest import synthetic_line


def test_parsed_pings_hold_no_samples(tmp_path, line, origin):
    path = tmp_path / "L0.xtf"
    write_xtf(line, path, origin)
    parsed = packets.parse_packets(path, 0)
    assert len(parsed.pings) == line.n_pings
    for ping in parsed.pings:
        assert all(isinstance(d, packets.FileSamples) for d in ping.data)
        assert [d.size for d in ping.data] == [line.n_bins, line.n_bins]
    # the offsets point at the samples pyxtf reads
    raw = np.frombuffer(path.read_bytes(), dtype=np.uint8)
    first = parsed.pings[0].data[1]  # starboard, nadir first
    stored = raw[first.offset : first.offset + first.nbytes].view(first.dtype)
    assert stored.size == line.n_bins and stored.max() > 0


def test_resampling_in_small_chunks_is_identical(tmp_path, origin, monkeypatch, caplog):
    """Chunks of one ping (a tiny resampling budget) and the file map's pages handed back
    every 4 kB, against one block per side: the same waterfall, altitudes, stats and log."""
    first = synthetic_line("A", n_pings=40, n_bins=96, max_range=40.0, seed=1)
    path = tmp_path / "A.xtf"
    write_xtf(first, path, origin)
    whole, stats = read_xtf(path, 64, origin=origin)
    whole_log = [r.getMessage() for r in caplog.records]
    caplog.clear()
    monkeypatch.setattr(packets, "RESAMPLE_BYTES", 8)
    monkeypatch.setattr(packets, "RELEASE_BYTES", 4096)  # hand back the map's pages often
    chunked, stats_c = read_xtf(path, 64, origin=origin)
    assert [r.getMessage() for r in caplog.records] == whole_log
    np.testing.assert_array_equal(chunked.intensity, whole.intensity)
    np.testing.assert_array_equal(chunked.altitude_m, whole.altitude_m)
    assert stats_c == stats
