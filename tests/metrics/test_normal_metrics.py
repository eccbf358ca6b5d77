"""Masked normal metrics against a NumPy reference; state sums merge (DDP-style)."""

import math

import numpy as np
import pytest
import torch

from sss2bathy.metrics import METRIC_NAMES, NormalDeltaAccuracy, NormalMAE, NormalMetrics


def reference(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    p = pred[mask].astype(np.float64)
    g = target[mask].astype(np.float64)
    err = np.abs(p - g)
    ratio = np.maximum((p + 1) / (g + 1), (g + 1) / (p + 1))
    return {
        "mae": err.mean(),
        "rel": (err / (g + 1)).mean(),
        "rmse": np.sqrt((err**2).mean()),
        "delta1": 100 * (ratio < 1.05).mean(),
        "delta2": 100 * (ratio < 1.05**2).mean(),
        "delta3": 100 * (ratio < 1.05**3).mean(),
    }


def random_batch(seed: int, shape=(4, 1, 16, 24), noise=0.06):
    rng = np.random.default_rng(seed)
    target = np.clip(rng.normal(0, 0.2, shape), -0.95, 0.95).astype(np.float32)
    pred = np.clip(target + rng.normal(0, noise, shape), -1, 1).astype(np.float32)
    mask = rng.random(shape) > 0.25
    return pred, target, mask


def update(metrics, pred, target, mask):
    metrics.update(torch.from_numpy(pred), torch.from_numpy(target), torch.from_numpy(mask))


def test_metrics_equal_numpy_reference():
    pred, target, mask = random_batch(0)
    target[0, 0, 0, :3] = np.nan  # invalid pixels may hold anything
    mask[0, 0, 0, :3] = False
    metrics = NormalMetrics()
    update(metrics, pred, target, mask)
    got = {k: float(v) for k, v in metrics.compute().items()}
    ref = reference(pred, target, mask)
    assert set(got) == set(METRIC_NAMES)
    for key in METRIC_NAMES:
        assert got[key] == pytest.approx(ref[key], rel=1e-5), key
    assert 0 < got["delta1"] < got["delta2"] < got["delta3"] <= 100


def test_update_in_two_halves_equals_once_and_states_merge():
    pred, target, mask = random_batch(1, shape=(6, 1, 8, 8))
    once = NormalMetrics()
    update(once, pred, target, mask)
    halves = NormalMetrics()
    update(halves, pred[:2], target[:2], mask[:2])
    update(halves, pred[2:], target[2:], mask[2:])
    # two "processes": separate metrics merged through their sum reductions
    a, b = NormalMAE(), NormalMAE()
    update(a, pred[:3], target[:3], mask[:3])
    update(b, pred[3:], target[3:], mask[3:])
    a.merge_state(b)
    expected = {k: float(v) for k, v in once.compute().items()}
    for key, value in halves.compute().items():
        assert float(value) == pytest.approx(expected[key], rel=1e-6)
    assert float(a.compute()) == pytest.approx(expected["mae"], rel=1e-6)
    assert all("sum" in fn.__name__ for fn in a._reductions.values())


def test_delta_metrics_equal_on_first_batch_stay_independent():
    # first batch: every pixel within 1.05^2 so delta2 == delta3 == 100 (equal states);
    # a collection that grouped them by equal state would report delta2 == delta3 later
    target = np.zeros((1, 1, 8, 8), np.float32)
    metrics = NormalMetrics()
    update(metrics, target + 0.06, target, np.ones_like(target, bool))
    update(metrics, target + 0.12, target, np.ones_like(target, bool))
    out = metrics.compute()
    assert float(out["delta2"]) == pytest.approx(50.0)
    assert float(out["delta3"]) == pytest.approx(100.0)


def test_prefix_empty_mask_and_validation():
    metrics = NormalMetrics(prefix="val/")
    zeros = torch.zeros(1, 1, 4, 4)
    metrics.update(zeros, zeros, torch.zeros(1, 1, 4, 4, dtype=torch.bool))
    out = metrics.compute()
    assert set(out) == {f"val/{k}" for k in METRIC_NAMES}
    assert all(math.isnan(float(v)) for v in out.values())
    with pytest.raises(ValueError, match="mask"):
        NormalMAE().update(zeros, zeros, torch.ones(1, 1, 4, 4))
    with pytest.raises(ValueError, match="target"):
        NormalMAE().update(zeros, zeros[..., :2], torch.ones(1, 1, 4, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="threshold"):
        NormalDeltaAccuracy(threshold=0.9)
