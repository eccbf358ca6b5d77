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


# ------------------------------------------------------------ baseline and bias
def test_masked_mean_pools_valid_bins_only():
    from sss2bathy.metrics.normal import masked_mean

    a = np.array([[0.1, 0.3], [np.nan, 5.0]])
    ma = np.array([[True, True], [False, False]])
    b = np.array([0.4])
    assert masked_mean([a, b], [ma, np.array([True])]) == pytest.approx((0.1 + 0.3 + 0.4) / 3)
    with pytest.raises(ValueError, match=r"masks\[0\].*bool"):
        masked_mean([a], [ma.astype(int)])
    with pytest.raises(ValueError, match="no.*found none|at least one valid bin"):
        masked_mean([a], [np.zeros_like(ma)])
    with pytest.raises(ValueError, match=r"values\[0\].*finite"):
        masked_mean([a], [np.ones_like(ma)])


def test_line_side_bias_against_numpy_reference():
    from sss2bathy.metrics.normal import LineSideBias

    rng = np.random.default_rng(3)
    n_bins, h, w = 12, 4, 8
    # two "lines" x two sides of full waterfalls, cut into windows at bin 0 and 4
    truth = rng.normal(0, 0.1, (2, 2, 2 * h, n_bins))
    pred = truth + 0.05 + 0.01 * np.arange(n_bins)  # bias growing with range
    valid = rng.random(truth.shape) > 0.3
    acc = LineSideBias()
    expect = np.zeros((2, 2, 3, n_bins))  # line, side, (pred, truth, count), bin
    for li in range(2):
        for si in range(2):
            for p0 in (0, h):
                for b0 in (0, 4):
                    sl = (li, si, slice(p0, p0 + h), slice(b0, b0 + w))
                    m = valid[sl]
                    acc.update(
                        torch.tensor(pred[sl][None, None]),
                        torch.tensor(truth[sl][None, None]),
                        torch.tensor(m[None, None]),
                        torch.tensor([li]),
                        torch.tensor([si]),
                        torch.tensor([b0]),
                    )
                    expect[li, si, 0, b0 : b0 + w] += (pred[sl] * m).sum(0)
                    expect[li, si, 1, b0 : b0 + w] += (truth[sl] * m).sum(0)
                    expect[li, si, 2, b0 : b0 + w] += m.sum(0)
    rows = acc.line_side_rows()
    assert [(r["line"], r["side"]) for r in rows] == [(0, 0), (0, 1), (1, 0), (1, 1)]
    for r in rows:
        e = expect[r["line"], r["side"]].sum(1)
        assert r["count"] == e[2]
        assert r["mean_pred"] == pytest.approx(e[0] / e[2])
        assert r["mean_truth"] == pytest.approx(e[1] / e[2])
        assert r["bias"] == pytest.approx((e[0] - e[1]) / e[2])
    ranged = acc.range_rows(3)
    assert [r["range_bin"] for r in ranged] == [0, 1, 2, 0, 1, 2]
    biases = [r["bias"] for r in ranged if r["side"] == 0]
    assert biases == sorted(biases) and biases[0] > 0.05  # the bias grows with range
    first = ranged[0]
    e = expect[:, 0, :, first["bin_lo"] : first["bin_hi"]].sum(axis=(0, 2))
    assert first["bias"] == pytest.approx((e[0] - e[1]) / e[2])
    with pytest.raises(ValueError, match="n_range_bins"):
        acc.range_rows(0)
    with pytest.raises(ValueError, match="mask: expected dtype"):
        acc.update(*(torch.zeros(1, 1, 2, 2),) * 3, *(torch.zeros(1, dtype=torch.long),) * 3)
