"""Hydra entry points only: compose a config, instantiate, run. No algorithms here.

Importing this package sets the thread policy's environment defaults
(:func:`sss2bathy.utils.threads.set_env_defaults`): every entry point imports it before
torch, and the OpenMP runtime reads its wait policy once, when torch loads it.
"""

from sss2bathy.utils.threads import set_env_defaults

set_env_defaults()
