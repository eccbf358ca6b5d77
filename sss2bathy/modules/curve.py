"""Moved to :mod:`sss2bathy.callbacks.curve`; this name stays until ``cli/train.py`` and
``eval/schedule_study.py`` import the new one."""

from sss2bathy.callbacks.curve import BASE_COLUMNS, MetricCurve, read_curve, write_curve

__all__ = ["BASE_COLUMNS", "MetricCurve", "read_curve", "write_curve"]
