"""Small FMI 3.0 FMUs with known answers, for the orchestrator's host tests.

``Signal`` outputs a polynomial of time, ``Echo`` reports the inputs it stepped with, and
``Faulty`` fails (error status or process abort) at a requested time. They are built with the
project's FMI layer, as the project's FMUs are, so they behave like them towards a host.
"""
