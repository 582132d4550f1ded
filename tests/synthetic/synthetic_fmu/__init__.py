"""Small FMI 3.0 slaves with known answers, for the orchestrator's host tests.

``Signal`` outputs a polynomial of time, ``Echo`` reports the inputs it stepped with, and
``Faulty`` fails (error status or process abort) at a requested time. They use the same
``GuardedSlaveMixin`` as the project's FMUs, so they behave like them towards a host.
"""
