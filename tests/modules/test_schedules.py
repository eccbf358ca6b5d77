"""The wall-clock learning-rate decay of siren_schedule=budget."""

from __future__ import annotations

import pytest
import torch

from sss2bathy.modules.schedules import WallClockExponentialLR


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _opt(lr: float = 1e-3) -> torch.optim.Optimizer:
    return torch.optim.Adam([torch.nn.Parameter(torch.zeros(2))], lr=lr)


def test_rate_follows_the_clock_and_ends_at_the_whole_decay():
    clock = FakeClock()
    opt = _opt()
    sched = WallClockExponentialLR(opt, gamma=0.7, budget_s=60.0, decay_epochs=10, clock=clock)
    assert opt.param_groups[0]["lr"] == pytest.approx(1e-3)
    for t, epochs in ((15.0, 2.5), (30.0, 5.0), (60.0, 10.0), (600.0, 10.0)):
        clock.t = 100.0 + t
        opt.step()
        sched.step()
        assert opt.param_groups[0]["lr"] == pytest.approx(1e-3 * 0.7**epochs, rel=1e-6)
    assert WallClockExponentialLR.interval == "step"


def test_a_resumed_scheduler_continues_its_decay():
    clock = FakeClock()
    opt = _opt()
    sched = WallClockExponentialLR(opt, gamma=0.5, budget_s=100.0, decay_epochs=4, clock=clock)
    clock.t += 50.0
    opt.step()
    sched.step()
    state = sched.state_dict()
    assert state["elapsed_s"] == pytest.approx(50.0) and "clock" not in state
    # a new process: its clock starts elsewhere, the elapsed time comes from the state
    later = FakeClock()
    later.t = 5000.0
    opt2 = _opt()
    resumed = WallClockExponentialLR(opt2, gamma=0.5, budget_s=100.0, decay_epochs=4, clock=later)
    resumed.load_state_dict(state)
    later.t += 25.0
    opt2.step()
    resumed.step()
    assert opt2.param_groups[0]["lr"] == pytest.approx(1e-3 * 0.5 ** (4 * 0.75), rel=1e-6)


@pytest.mark.parametrize(
    "kw, message",
    [
        ({"budget_s": 0.0}, "budget_s: expected a positive number of seconds, found 0.0"),
        ({"gamma": 1.5}, "gamma: expected a decay factor in (0, 1], found 1.5"),
        ({"decay_epochs": -1}, "decay_epochs: expected a positive number of epochs, found -1"),
    ],
)
def test_bad_settings_are_named(kw, message):
    args = {"gamma": 0.7, "budget_s": 10.0, "decay_epochs": 10, **kw}
    with pytest.raises(ValueError) as err:
        WallClockExponentialLR(_opt(), **args)
    assert str(err.value).startswith(message)
