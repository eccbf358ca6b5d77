"""Synthetic surveys: seafloor, survey plan and a ray-traced, non-Lambertian sidescan.

Entry points: :func:`sss2bathy.sim.prepare.prepare_synthetic` (cached survey folder),
:func:`sss2bathy.sim.generate.generate_survey` (in memory),
:func:`sss2bathy.sim.sonar.simulate_pings` (the physics on any mesh) and
:mod:`sss2bathy.sim.render` (pictures).
"""
