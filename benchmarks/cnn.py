"""Section ``cnn``: normal-CNN training steps on 64 x 512 windows at the demo and paper sizes.

:class:`~sss2bathy.models.normal_cnn.NormalResNet` + :class:`~sss2bathy.losses.normal.NormalLoss`
+ Adam, with the network sizes, batch and loss of the CNN experiment composed at each
scale (``experiment=cnn scale=demo|paper``): windows/s.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from benchmarks.config import cnn_preset
from benchmarks.timing import figure, rates, resolve_device, time_runs

TITLE = "CNN training"
SIZE_KEYS = ("base_width", "n_blocks", "batch_size")


def bench_cnn(
    *,
    root: str | Path | None = None,
    scales: Sequence[str] = ("demo", "paper"),
    configs: Mapping[str, Mapping[str, Any]] | None = None,
    window: tuple[int, int] = (64, 512),
    max_batch: int | None = None,
    warmup: int = 1,
    repeats: int = 5,
    lr: float = 2e-4,
    device: str | torch.device | None = None,
    seed: int = 0,
) -> dict:
    """CNN training steps (forward, normal-aware loss + TV, backward, Adam): windows/s.

    Args:
        root: the project root whose ``conf/`` is composed (see :mod:`benchmarks.config`).
        scales: the scales whose CNN experiment is measured (when ``configs`` is ``None``).
        configs: ``{name: {base_width, n_blocks, batch_size[, n_down, loss]}}`` in place of
            the composed ones; without ``n_down``, the paper's 2; without ``loss``, the demo
            experiment's loss.
        window: ``(pings, bins)`` of a window.
        max_batch: cap on the batch (a CPU may need minutes for a step of the paper's
            batch); windows/s is reported for the batch actually run.
    """
    from sss2bathy.losses.normal import NormalLoss
    from sss2bathy.models.normal_cnn import N_DOWN, NormalResNet

    dev = resolve_device(device)
    if configs is None:
        configs = {scale: cnn_preset(root, scale) for scale in scales}
    default_loss = None
    figures, params = [], {}
    for name, c in configs.items():
        missing = [k for k in SIZE_KEYS if k not in c]
        if missing:
            raise ValueError(f"configs.{name}: expected keys {list(SIZE_KEYS)}, missing {missing}")
        if "loss" not in c and default_loss is None:
            default_loss = cnn_preset(root, "demo")["loss"]
        loss_fn = NormalLoss.from_config(c.get("loss", default_loss))
        torch.manual_seed(seed)
        batch = int(c["batch_size"]) if max_batch is None else min(int(c["batch_size"]), max_batch)
        n_down = int(c.get("n_down", N_DOWN))
        net = NormalResNet(
            base_width=int(c["base_width"]), n_blocks=int(c["n_blocks"]), n_down=n_down
        ).to(dev)
        opt = torch.optim.Adam(net.parameters(), lr=lr)
        gen = torch.Generator().manual_seed(seed)
        h, w = window
        x = torch.rand(batch, 1, h, w, generator=gen).to(dev)
        target = ((torch.rand(batch, 1, h, w, generator=gen) - 0.5) * 0.8).to(dev)
        mask = (torch.rand(batch, 1, h, w, generator=gen) < 0.8).to(dev)

        def step(net=net, opt=opt, x=x, target=target, mask=mask, loss_fn=loss_fn) -> None:
            opt.zero_grad(set_to_none=True)
            loss_fn(net(x), target, mask)["loss"].backward()
            opt.step()

        times = time_runs(step, warmup, repeats, dev)
        note = f"width {c['base_width']}, {c['n_blocks']} blocks, n_down {n_down}, batch {batch}"
        if batch != int(c["batch_size"]):
            note += f" (configured {c['batch_size']}; capped on {dev.type})"
        figures.append(figure(f"{name}: windows/s", "windows/s", rates(batch, times), note))
        figures.append(figure(f"{name}: step time", "s", times))
        params[name] = {**{k: int(c[k]) for k in SIZE_KEYS}, "n_down": n_down, "batch_run": batch}
    return {
        "title": TITLE,
        "params": {"window": list(window), "configs": params, "device": str(dev)},
        "figures": figures,
        "info": {},
        "notes": (
            "NormalResNet + NormalLoss (the CNN experiment's loss at its scale) + Adam on "
            f"random {window[0]} x {window[1]} windows, 80 % valid pixels."
        ),
    }
