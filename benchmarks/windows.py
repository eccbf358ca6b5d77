"""Section ``windows``: the normal CNN's training batches assembled by the window loader.

The pretraining recipe's windows (64 x 256, batch 32, flips, intensity + grazing + range) cut
from random lines of a 512-bin sonar by :class:`~sss2bathy.data.windows.SidescanWindowDataset`
and collated as a data-loader worker does, then copied to the device: batches/s of one
process, no network. A GPU run with ``data.num_workers`` workers is fed at about that many
times this rate; compare it with the network's steps/s (section ``cnn``).
"""

from __future__ import annotations

import numpy as np
import torch

from benchmarks.timing import figure, rates, resolve_device, time_runs

TITLE = "CNN window batches"


def _lines(n_lines: int, n_pings: int, n_bins: int, seed: int) -> list:
    from sss2bathy.data.windows import WindowLine

    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_lines):
        shape = (n_pings, 2, n_bins)
        valid = rng.random(shape) > 0.2
        out.append(
            WindowLine(
                f"l{i}",
                rng.random(shape, dtype=np.float32),
                np.where(valid, rng.random(shape, dtype=np.float32) - 0.5, 0).astype(np.float32),
                valid,
                altitude_m=np.full(n_pings, 8.0, np.float32),
                range_m=np.linspace(0.1, 30.0, n_bins, dtype=np.float32),
                channels=("intensity", "grazing", "range"),
            )
        )
    return out


def bench_windows(
    *,
    n_lines: int = 16,
    n_pings: int = 300,
    n_bins: int = 512,
    window: tuple[int, int] = (64, 256),
    batch: int = 32,
    n_batches: int = 8,
    warmup: int = 1,
    repeats: int = 5,
    device: str | torch.device | None = None,
    seed: int = 0,
) -> dict:
    """Batches/s of the training loader's work in one process (``__getitem__`` of each
    window, the default collate, the copy to ``device``)."""
    from torch.utils.data import default_collate

    from sss2bathy.data.windows import FlipShuffleSampler, SidescanWindowDataset

    dev = resolve_device(device)
    ds = SidescanWindowDataset(
        _lines(n_lines, n_pings, n_bins, seed), window[0], window[1], 0.75, 0.2, True,
        overlap_bins=0.5,
    )  # fmt: skip
    items = list(FlipShuffleSampler(len(ds), seed=seed))
    chunks = [items[i * batch : (i + 1) * batch] for i in range(n_batches)]

    def assemble() -> None:
        for c in chunks:
            b = default_collate([ds[i] for i in c])
            _ = {k: v.to(dev) for k, v in b.items()}

    times = time_runs(assemble, warmup, repeats, dev)
    return {
        "title": TITLE,
        "params": {
            "lines": n_lines,
            "pings": n_pings,
            "bins": n_bins,
            "window": list(window),
            "batch": batch,
            "windows": len(ds),
            "device": str(dev),
        },
        "figures": [figure("batches/s (one process)", "batches/s", rates(n_batches, times))],
        "info": {},
        "notes": (
            f"{n_batches} batches of {batch} windows {window[0]} x {window[1]} (flips "
            "included) from random lines, 3 input channels: items, collate, copy to the "
            "device, in one process; no network."
        ),
    }
