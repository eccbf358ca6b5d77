"""Hydra entry points only: compose a config, instantiate, run. No algorithms here."""
