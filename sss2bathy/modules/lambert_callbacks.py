"""Moved to :mod:`sss2bathy.callbacks.lambert`; this name stays until the experiment configs
and tests that name it use the new one."""

from sss2bathy.callbacks.lambert import LambertCurvesLogger

__all__ = ["LambertCurvesLogger"]
