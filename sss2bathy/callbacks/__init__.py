"""Lightning callbacks of the fits, in one package (configured in ``conf/callbacks/``, or
added by a module's ``configure_callbacks``).

* :mod:`~sss2bathy.callbacks.checkpoint`: the resumable ``last.ckpt`` (every epoch, every N
  steps, on SIGTERM / SIGINT), atomic checkpoint writes;
* :mod:`~sss2bathy.callbacks.guard`: non-finite step guard, global RNG state in checkpoints;
* :mod:`~sss2bathy.callbacks.curve`: ``metric_curve.csv`` (metric against time);
* :mod:`~sss2bathy.callbacks.hparams`: the run's HPARAMS record (identity, parameters,
  final metrics);
* :mod:`~sss2bathy.callbacks.images`: TensorBoard images (CNN windows, SIREN maps);
* :mod:`~sss2bathy.callbacks.lambert`: the Lambertian sensor's learned curves and waterfall;
* :mod:`~sss2bathy.callbacks.writers`: the CNN table and bias files, the SIREN map export,
  the full-name test metrics table.

Callbacks read what a module exposes (``latest_evaluation``, ``final_map()``,
``sidescan_geometry()``, ``test_set_name()``) and import nothing from ``modules``.
"""

from sss2bathy.callbacks.checkpoint import (
    AtomicCheckpointIO,
    Interruption,
    LastCheckpoint,
    interruption,
    use_atomic_checkpoints,
)
from sss2bathy.callbacks.curve import MetricCurve, read_curve, write_curve
from sss2bathy.callbacks.guard import (
    GlobalRNGState,
    NonFiniteGuard,
    NonFiniteTrainingError,
    global_rng_state,
    set_global_rng_state,
)
from sss2bathy.callbacks.hparams import RunHparams
from sss2bathy.callbacks.images import NormalImageLogger, SirenMapImages, render_window_panel
from sss2bathy.callbacks.lambert import LambertCurvesLogger
from sss2bathy.callbacks.writers import (
    CNNTableWriter,
    MetricsTableLogger,
    SirenMapExport,
    metrics_table,
)

__all__ = [
    "AtomicCheckpointIO",
    "Interruption",
    "LastCheckpoint",
    "CNNTableWriter",
    "GlobalRNGState",
    "LambertCurvesLogger",
    "MetricCurve",
    "NonFiniteGuard",
    "NonFiniteTrainingError",
    "NormalImageLogger",
    "RunHparams",
    "SirenMapExport",
    "SirenMapImages",
    "MetricsTableLogger",
    "global_rng_state",
    "interruption",
    "metrics_table",
    "read_curve",
    "render_window_panel",
    "set_global_rng_state",
    "use_atomic_checkpoints",
    "write_curve",
]
