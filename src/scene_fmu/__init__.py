"""A whole scene as one FMI 3.0 Co-Simulation FMU with scalar ports (``python -m orchestration export
SCENE --fmu OUT.fmu``).

For masters without FMI 3 arrays or multirate support (Ecos, the fmu-manipulation-toolbox's
containers, a PLC's runtime): the scene's orchestrator runs inside the FMU, exact (the same steps
and values as ``python -m orchestration run``), its FMUs carried in ``resources/scene_fmu/fmus``
and run in the FMU's process, the orchestrator in ``resources/scene_fmu/vendor``. The scene's
sources (the operator's script) become scalar inputs, the ports it records scalar outputs; the
FMU steps at the scene's fastest rate. What the export chose is in ``scene_fmu.json`` beside this
file (written by ``orchestration/app/scene_fmu.py``); :mod:`.fmu` declares the FMU from it.
"""
