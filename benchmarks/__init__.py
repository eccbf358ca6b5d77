"""Benchmarks of the pipeline's hot paths, measured on whatever machine runs them.

Not part of the installed package: run from the checkout, ``python -m benchmarks``
(``make bench``, :mod:`benchmarks.runner`), which writes ``outputs/bench/bench.json`` and
``outputs/bench/bench.md``. One module per section:

* ``siren_step`` (:mod:`benchmarks.siren_step`) — one SIREN training step through
  ``SirenModule.model_step``, its throughput and its matmul bound (:mod:`benchmarks.matmul`);
* ``finder`` (:mod:`benchmarks.finder`) — the intersection finder: paper GD vs Newton and
  secant, cold and warm;
* ``cnn`` (:mod:`benchmarks.cnn`) — normal-CNN training steps at the demo and paper sizes;
* ``sim`` (:mod:`benchmarks.simulator`) — the sidescan simulator on a preset;
* ``drape`` (:mod:`benchmarks.draping`) — draping against the bare ray casts;
* ``gpu_projection`` (:mod:`benchmarks.projection`) — derived: the paper-scale fit's
  minutes on GPUs from the ``siren_step`` section;
* ``demo_stages`` (:mod:`benchmarks.demo_stages`) — the last ``make demo``'s stage times.

Shared: the timing helper (:mod:`benchmarks.timing`: warm-up, repeats, median and spread,
CUDA synchronisation), the synthetic SIREN scene (:mod:`benchmarks.scene`), the composed
configs (:mod:`benchmarks.config`), the report (:mod:`benchmarks.report`).
"""
