"""What a scene is once loaded: its components, connections, recording; the plausibility limits of its
times."""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from fractions import Fraction
from pathlib import Path

from orchestration.hosts.description import FmuDescription, PortInfo


class Ordering(StrEnum):
    """When a connection's consumer reads its producer: the value at the end of its step (the
    producer steps first) or at its start (both step at once)."""

    GAUSS_SEIDEL = "gauss-seidel"
    JACOBI = "jacobi"


class Hosting(StrEnum):
    """Where an FMU runs: in the master's process, or in a worker process of its own."""

    IN_PROCESS = "in-process"
    OUT_OF_PROCESS = "out-of-process"


ORDERINGS = tuple(Ordering)
HOSTINGS = tuple(Hosting)
#: what a connection uses when the scene names no ordering
DEFAULT_ORDERING = Ordering.GAUSS_SEIDEL
#: where a scene's FMUs run when neither the scene nor the command line says
DEFAULT_HOSTING = Hosting.OUT_OF_PROCESS

# -- plausibility limits: values no scene of this project can mean ---------------------------------
#: The shortest communication step, s. The fastest loop here is the 1 kHz haptic loop (studies go
#: down to 4 kHz); a step below 1 us is a typo (a unit slip) and would take hours per simulated second.
MIN_STEP = Fraction(1, 10**6)
#: The longest communication step, s. The slowest component, the tissue, steps at 30 Hz (studies
#: down to 10 Hz); a step above 1 s cannot track a haptic interaction at all.
MAX_STEP = Fraction(1)
#: The most component steps one run may take (the sum over stepped components of duration / step).
#: This machine makes about 3500 steps per second of wall time (the default scene: 8120 steps in
#: 2.3 s), so the limit is about 50 minutes of computing: a longer run is almost always a duration
#: in ms typed as s. It is refused, not warned about, so that `validate` and the exit code stop a
#: script or study before it blocks a machine for hours; split a genuinely long session into runs.
MAX_RUN_STEPS = 10_000_000
#: The deepest nesting of tables and lists a scene may have. The format nests at most 5 levels
#: ([record] plots, panels, series, a table); far deeper nesting is no scene, and would exhaust
#: the interpreter's recursion limit (the TOML parser's, and ours) with a RecursionError, or (dotted
#: keys) the parser's memory. Checked on the text before parsing (``nesting_problem``) and on the
#: parsed tree (``too_deep``: scene_from_dict is also given trees that never were text).
MAX_NESTING = 32


class SceneError(ValueError):
    """A scene has problems; ``problems`` lists every one ("where: what is wrong; the fix")."""

    def __init__(self, path, problems: list[str]):
        self.path = Path(path) if path is not None else None
        self.problems = list(problems)
        head = f"{self.path}: " if self.path else ""
        count = f"{len(self.problems)} problem{'s' if len(self.problems) != 1 else ''}"
        super().__init__(f"{head}{count}\n" + "\n".join(f"  - {p}" for p in self.problems))


@dataclass
class ComponentSpec:
    """One component of a scene: an FMU, a stepped block or a continuous source."""

    name: str
    kind: str                                   # "fmu", or a block kind ("device_plant", "piecewise_linear", ...)
    step: Fraction | None                       # None for continuous sources
    parameters: dict = field(default_factory=dict)
    path: Path | None = None                    # FMUs
    table: dict = field(default_factory=dict)   # blocks: their TOML table
    ports: dict[str, PortInfo] = field(default_factory=dict)
    description: FmuDescription | None = None
    base_dir: Path | None = None                # blocks: where their relative paths start
    hosting: str | None = None                  # FMUs: "in-process" | "out-of-process" (None: the scene's)
    #: what ``validate`` and a run say about the component that is no error (a step passed on to the FMU)
    notes: list[str] = field(default_factory=list)

    def new_block(self):
        """A fresh instance of a block or source (each run gets its own: a scene is data)."""
        from orchestration.blocks.registry import make_block

        return make_block(self.name, self.table, self.base_dir)

    @property
    def is_fmu(self) -> bool:
        return self.kind == "fmu"

    @property
    def is_continuous(self) -> bool:
        return self.step is None


@dataclass(frozen=True)
class ConnectionSpec:
    source: str
    source_port: str
    target: str
    target_port: str
    transition: str | None
    ordering: str
    index: int

    @property
    def label(self) -> str:
        return f"connection {self.index} ({self.source}.{self.source_port} -> {self.target}.{self.target_port})"


@dataclass(frozen=True)
class SurfaceSpec:
    component: str
    positions: str
    triangles: str
    every: int = 1
    point_data: tuple[str, ...] = ()
    name: str = "surface"


@dataclass
class Scene:
    path: Path | None
    name: str
    description: str
    duration: Fraction
    components: dict[str, ComponentSpec]
    connections: list[ConnectionSpec]
    record: dict[str, list[str]]
    surfaces: list[SurfaceSpec]
    plots: list[dict]
    summary: dict
    hosting: str = DEFAULT_HOSTING
    realtime: bool = False
    #: run-faults (issue 14): seconds a worker process may take to answer during the run;
    #: None: automatic, max(10 s, 100 x its slowest recent reply) (see orchestration.hosts.worker)
    worker_timeout: float | None = None

    @property
    def notes(self) -> list[str]:
        """What ``validate`` and a run report about the scene that is no error, component by component."""
        return [note for spec in self.components.values() for note in spec.notes]

    def incoming(self, component: str) -> list[ConnectionSpec]:
        return [c for c in self.connections if c.target == component]

    def outgoing(self, component: str) -> list[ConnectionSpec]:
        return [c for c in self.connections if c.source == component]
