"""The one set of setting checks: bounds declared once on a dataclass field (``setting``),
read by one generic reader (``read_fields``), one ``coerce_config``; every error one line
naming the key, the expected and the found value."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest

from sss2bathy.utils.checks import (
    ConfigReader,
    check_number,
    coerce_config,
    read_fields,
    require_int,
    setting,
)


@dataclass(frozen=True)
class Probe:
    name: str = "x"  # not a setting: left to the caller
    speed_mps: float = setting(2.0, gt=0.0)
    tilt_rad: float = setting(math.radians(25.0), "tilt_deg", unit="deg", ge=0.0, lt=90.0)
    khz_hz: float = setting(850e3, "frequency_khz", unit="khz", gt=0.0)
    n: int = setting(4, kind="integer", ge=1)
    mode: str = setting("a", kind="choice", choices=("a", "b"))
    ph: float = setting(8.0, "water.ph", ge=6.0, le=9.0)
    span: tuple[float, float] | None = setting(None, kind="optional_pair", unit="deg", gt=0.0)


def _read(data: dict) -> Probe:
    r = ConfigReader(data, "data.survey.sonar")
    values = read_fields(r, Probe)
    r.done()
    return Probe(**values)


def test_left_out_keys_take_the_field_default_and_given_ones_their_unit():
    assert _read({}) == Probe()
    p = _read({"tilt_deg": 30, "frequency_khz": 400, "water": {"ph": 7}, "span": [10, 20]})
    assert p.tilt_rad == math.radians(30) and p.khz_hz == 400e3 and p.ph == 7.0
    assert p.span == (math.radians(10), math.radians(20))


@pytest.mark.parametrize(
    "data, message",
    [
        ({"speed_mps": 0}, "data.survey.sonar.speed_mps: expected a number > 0.0, found 0"),
        ({"tilt_deg": 95}, "tilt_deg: expected a number >= 0.0 and < 90.0, found 95"),
        ({"tilt_deg": True}, "tilt_deg: expected a finite number, found True"),
        ({"n": 1.5}, "data.survey.sonar.n: expected an integer, found 1.5"),
        ({"mode": "c"}, "mode: expected one of ['a', 'b'], found 'c'"),
        ({"water": {"ph": 10}}, "data.survey.sonar.water.ph: expected a number >= 6.0 and <= 9.0"),
        ({"water": 3}, "data.survey.sonar.water: expected a mapping, found 3"),
        ({"span": [20, 10]}, "data.survey.sonar.span: expected low <= high, found [20, 10]"),
        ({"water": {"pH": 7}}, "data.survey.sonar.water: unknown key(s) ['pH']; expected some"),
        ({"speed": 1}, "data.survey.sonar: unknown key(s) ['speed']; expected some of"),
    ],
)
def test_a_bad_value_is_one_line_naming_the_full_key(data, message):
    with pytest.raises(ValueError) as err:
        _read(data)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_check_number_and_require_int_name_the_bounds():
    assert check_number("k", 3, gt=1, le=3) == 3.0
    with pytest.raises(ValueError, match=r"^k: expected a number > 1 and <= 3, found 4$"):
        check_number("k", 4, gt=1, le=3)
    with pytest.raises(ValueError, match=r"^k: expected a finite number, found nan$"):
        check_number("k", math.nan)
    with pytest.raises(ValueError, match=r"^n: expected an integer >= 0, found -1$"):
        require_int("n", -1, minimum=0)


def test_coerce_config_from_none_a_mapping_or_an_instance():
    assert coerce_config(Probe, None, "probe") == Probe()
    assert coerce_config(Probe, {"n": 7}, "probe").n == 7
    given = Probe(n=3)
    assert coerce_config(Probe, given, "probe") is given
    with pytest.raises(ValueError, match=r"^probe: expected a mapping or Probe, found list$"):
        coerce_config(Probe, [1], "probe")
    with pytest.raises(ValueError, match=r"^probe: unknown keys \['m'\]; expected some of"):
        coerce_config(Probe, {"m": 1}, "probe")
