"""Fixtures of these tests live in reliability_helpers.py (importable by name from the tests;
a module called conftest is not, when several test folders each have one)."""

from reliability_helpers import *  # noqa: F403
