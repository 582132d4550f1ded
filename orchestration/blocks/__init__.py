"""Built-in (non-FMU) components of the orchestrator: signal sources and the haptic device plant.

Sources are *continuous*: they have outputs only and ``evaluate(t)`` returns their exact values at
any time t (a pure function of t), so the master reads them where it needs them, with no step and
no rate transition.
- ``PiecewiseLinearSource``: scripted operator motion (e.g. a catheter insertion ramp).
- ``CsvSource``: playback of recorded motion from a CSV file.
- ``RigidSurfaceSource``: constant geometry (plane or tube) for the Contact FMU when no Tissue FMU runs.

``DevicePlant`` is a stepped component with the master's ``ComponentHost`` protocol (in process,
synchronous): the haptic device as a damped mass, integrated exactly over each step with its input
forces held (zero-order hold), with exact energy bookkeeping.

``registry.make_block(name, table, base_dir)`` builds any of them from a scene's TOML table and reports every
configuration problem at once (``BlockConfigError``). All port values are 1-D float64 arrays.

Modules: ``sources`` (piecewise-linear), ``csv_source``, ``surfaces``, ``plant`` (the device), ``options``
(the checks of a block's options), ``registry`` (the kinds, their options, ``make_block``).
"""
