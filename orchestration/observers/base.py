"""The observer interface: every event of a run, as a method.

The algorithm (:class:`~orchestration.run.algorithm.MultirateAlgorithm`) tells each observer of
the run's events; an observer never changes what the components compute. A new observer
subclasses :class:`Observer` and overrides the events it needs; the others do nothing.
"""
from __future__ import annotations

import numpy as np


class Observer:
    """An observer of a run. Events, in the order they come:

    ``initializing`` and ``initialized`` (around the components' initialization), ``started``
    (the first step follows), per step of a component it subscribes to ``before_step`` (only when
    ``times_steps``) and ``stepped``, or, after a stretch of steps run in C by the compiled loop,
    ``stepped_block`` and ``paced_block``; ``finished`` however the run ends.
    """

    #: True: ``before_step`` is called before each step of the components it subscribes to. Timing
    #: steps keeps those components out of the compiled loop, unless the observer ``paces``.
    times_steps: bool = False
    #: True: it paces steps in real time as the compiled program can itself
    #: (:class:`~orchestration.observers.pacing.RealtimePacing`), and learns how late each paced
    #: step was from ``paced_block``.
    paces: bool = False
    #: False: it subscribes to steps by ``subscribes``, not by the ports it names, so it may read
    #: outputs the compiled loop would not copy for it; those components then step in Python.
    names_its_ports: bool = True

    def ports(self, component: str) -> list[str]:
        """The ports of ``component`` it reads (the algorithm then gets them from every step)."""
        return []

    def subscribes(self, component) -> bool:
        """Whether it is told of ``component``'s steps (default: when it reads any of its ports)."""
        return bool(self.ports(component.name))

    def initializing(self, algorithm) -> None:
        """The components are instantiated, before their initialization."""

    def initialized(self, algorithm) -> None:
        """The components left Initialization Mode; their initial outputs are available."""

    def started(self, algorithm) -> None:
        """The first step comes next."""

    def before_step(self, component, tick: int) -> None:
        """``component`` is about to step from ``tick`` (only when ``times_steps``)."""

    def stepped(self, component, tick: int, outputs: dict[str, np.ndarray]) -> None:
        """``component`` reached ``tick``; ``outputs`` (its observed ports) are valid only during the call."""

    def stepped_block(self, component, ticks: list[int], outputs: dict[str, np.ndarray], first_step: int) -> None:
        """Steps run by the compiled loop, in time order: ``outputs[port]`` has a row per step of
        ``ticks``, the first of them ``component``'s step number ``first_step``. Default: ``stepped``
        per step, with ``component.steps`` as it was after each."""
        steps_after = component.steps
        for i, tick in enumerate(ticks):
            component.steps = first_step + i + 1
            self.stepped(component, tick, {name: values[i] for name, values in outputs.items()})
        component.steps = steps_after

    def paced_block(self, component, lateness: np.ndarray) -> None:
        """How late each paced step of a compiled stretch ended, in seconds (only when ``paces``)."""

    def finished(self, algorithm) -> None:
        """The run ended (completed, stopped or failed); resources can be given back."""
