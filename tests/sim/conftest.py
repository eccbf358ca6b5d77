"""Fixtures of these tests live in sim_helpers.py (importable by name from the tests;
a module called conftest is not, when several test folders each have one)."""

from sim_helpers import *  # noqa: F403
