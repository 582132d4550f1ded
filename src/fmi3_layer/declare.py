"""How an FMU of this project declares its interface: one table of variables beside its model.

Each FMU package links this file as ``<package>/_fmi.py`` and declares, in its ``fmu.py``, one
:class:`FmuDeclaration`: the variables (name, type, causality, variability, unit, description,
start value, array dimensions) and the class that connects them to the model. Everything else is
generated from that table: the modelDescription.xml (``fmi3_runtime.model_description``), the
variable table of the C layer, the start values, and the ``values`` object through which the
model reads parameters and inputs and writes outputs. Plain Python, no FMI calls, no numpy.

The connecting class (the "adapter") is plain Python:

- ``__init__(self, values)`` builds the model from the parameters (raise ``ValueError`` with a
  message that names the parameter and the fix) and writes the initial outputs;
- ``step(self, t, dt)`` advances one internal step of ``dt`` seconds, reading inputs from and
  writing outputs to the ``values`` it kept;
- optional ``terminate(self)``.

``values.set_count(name)`` says how often the importer set a variable; ``values.resource_folder()``
is the instance's extracted ``resources/`` (for files the FMU carries: the package may have been
imported from an earlier instance's folder, since removed).

Its attributes (other than the ``values``) are the model state that fmi3GetFMUState saves, so
they must survive ``copy.deepcopy`` and ``pickle``.

The ``values`` arrays are views of the FMU's own memory (what ``fmi3Get*`` copies out), so a
model may compute an output straight into one instead of returning an array the adapter copies
(``model.write_outputs_into(values.x, ...)``; the 1 kHz FMUs do, see their ``fmu.py``). A
restored FMU state holds a copy of the model, which writes into arrays of its own: the adapter
notices (the array the step returned is not ``values.x``) and binds it again.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from dataclasses import fields as dataclasses_fields
from typing import Any, Callable

#: Units used by the project's ports: name -> SI base-unit exponents (docs/design.md section 4).
SI_UNITS: dict[str, dict[str, int]] = {
    "m": dict(m=1),
    "s": dict(s=1),
    "N": dict(kg=1, m=1, s=-2),
    "Pa": dict(kg=1, m=-1, s=-2),
    "J": dict(kg=1, m=2, s=-2),
    "kg/m3": dict(kg=1, m=-3),
    "Pa.s": dict(kg=1, m=-1, s=-1),
    "m/s": dict(m=1, s=-1),
    "N/m": dict(kg=1, s=-2),
    "N/s": dict(kg=1, m=1, s=-3),
    "m/N": dict(kg=-1, s=2),
    "N.s/m": dict(kg=1, s=-1),
    "rad": dict(rad=1),
    "rad/s": dict(rad=1, s=-1),
    "Hz": dict(s=-1),
    "N.m2": dict(kg=1, m=3, s=-2),
}

TYPES = ("Float64", "Int32", "UInt64", "Boolean", "String")
CAUSALITIES = ("parameter", "calculatedParameter", "structuralParameter", "input", "output", "independent")
VARIABILITIES = ("constant", "fixed", "tunable", "discrete", "continuous")


@dataclass(frozen=True)
class Limit:
    """The plausible range of a number an importer gives (a parameter, an input, an array size).

    A value outside it cannot be meant (a typing error, a unit mistake, a broken connection) and
    would give an absurd or endless computation, so the FMU refuses it with this reason: Float64
    values in ``fmi3SetFloat64``, every parameter again at ``fmi3ExitInitializationMode`` and
    structural parameters at ``fmi3ExitConfigurationMode``. The range becomes the variable's
    ``min``/``max`` in modelDescription.xml and its description says why."""

    minimum: float
    maximum: float
    why: str

    def __post_init__(self):
        if not (math.isfinite(self.minimum) and math.isfinite(self.maximum) and self.minimum <= self.maximum):
            raise ValueError(f"a limit needs finite minimum <= maximum (got {self.minimum}, {self.maximum})")
        if not self.why:
            raise ValueError("a limit must say why (what a value beyond it would mean)")

    def text(self, unit: str | None) -> str:
        """``[min, max] unit: why``, as error messages and the description give it."""
        return f"[{_shortest(self.minimum)}, {_shortest(self.maximum)}]{' ' + unit if unit else ''}: {self.why}"


def _shortest(x: float) -> str:
    """The shortest text that reads back as ``x`` (1e-06, not 9.9999999999999995e-07)."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e16 else repr(float(x))


@dataclass(frozen=True)
class Variable:
    """One variable of an FMU. ``shape`` holds ints and names of structural parameters."""

    name: str
    type: str
    causality: str
    variability: str
    start: Any = None
    unit: str | None = None
    description: str = ""
    shape: tuple = ()
    #: the plausible range (from the FMU's limit table, FmuDeclaration.limits), or None
    limit: Limit | None = None

    def __post_init__(self):
        if self.type not in TYPES:
            raise ValueError(f"{self.name}: type {self.type!r} is not one of {TYPES}")
        if self.causality not in CAUSALITIES:
            raise ValueError(f"{self.name}: causality {self.causality!r} is not one of {CAUSALITIES}")
        if self.variability not in VARIABILITIES:
            raise ValueError(f"{self.name}: variability {self.variability!r} is not one of {VARIABILITIES}")
        if self.unit is not None and self.unit not in SI_UNITS:
            raise ValueError(f"{self.name}: unit {self.unit!r} is not declared in SI_UNITS")
        if self.shape and self.type == "String":
            raise ValueError(f"{self.name}: String arrays are not supported")
        if self.limit is not None:
            if self.type not in ("Float64", "Int32", "UInt64"):
                raise ValueError(f"{self.name}: only numbers have limits (it is a {self.type})")
            starts = () if self.start is None or callable(self.start) else _flat_numbers(self.start)
            outside = [x for x in starts if not self.limit.minimum <= x <= self.limit.maximum]
            if outside:
                raise ValueError(f"{self.name}: start value {outside[0]!r} is outside its limit "
                                 f"{self.limit.text(self.unit)}")

    def outside_limit(self, value: float) -> str | None:
        """Why ``value`` is refused ("above the maximum ..."), or None when it is within the limit."""
        limit = self.limit
        if limit is None or limit.minimum <= value <= limit.maximum:
            return None
        if value != value:
            return "not a number"
        side = "below the minimum" if value < limit.minimum else "above the maximum"
        return f"{side} of its plausible range {limit.text(self.unit)}"

    @property
    def has_start(self) -> bool:
        """Parameters and inputs carry start values; outputs and calculated parameters do not."""
        return self.causality in ("parameter", "structuralParameter", "input")


def _flat_numbers(value) -> list[float]:
    """The numbers of a start value (a number or nested sequences of them)."""
    if isinstance(value, (list, tuple)) or hasattr(value, "tolist"):
        items = value.tolist() if hasattr(value, "tolist") else value
        if not isinstance(items, (list, tuple)):
            return [float(items)]
        return [x for item in items for x in _flat_numbers(item)]
    return [float(value)]


def _type_of(value) -> str:
    if isinstance(value, bool):
        return "Boolean"
    if isinstance(value, int):
        return "Int32"
    if isinstance(value, str):
        return "String"
    return "Float64"


def parameter(name: str, start, description: str, unit: str | None = None, *, type: str | None = None,
              shape: tuple = (), tunable: bool = False) -> Variable:
    """A parameter, fixed unless ``tunable``; its type follows the start value unless given."""
    return Variable(name, type or _type_of(start), "parameter", "tunable" if tunable else "fixed", start, unit,
                    description, tuple(shape))


def structural(name: str, start: int, description: str) -> Variable:
    """A structural parameter (UInt64) that sizes arrays; set in Configuration Mode."""
    return Variable(name, "UInt64", "structuralParameter", "fixed", int(start), None, description)


def input_port(name: str, description: str, unit: str | None = None, *, shape: tuple = (), start=0.0,
               type: str = "Float64") -> Variable:
    variability = "continuous" if type == "Float64" else "discrete"
    return Variable(name, type, "input", variability, start, unit, description, tuple(shape))


def output(name: str, description: str, unit: str | None = None, *, shape: tuple = (),
           type: str = "Float64") -> Variable:
    variability = "continuous" if type == "Float64" else "discrete"
    return Variable(name, type, "output", variability, None, unit, description, tuple(shape))


def calculated(name: str, description: str, *, shape: tuple = (), type: str = "Float64",
               unit: str | None = None) -> Variable:
    """A calculated parameter: computed by the FMU when it is built (e.g. the mesh's triangles)."""
    return Variable(name, type, "calculatedParameter", "fixed", None, unit, description, tuple(shape))


@dataclass(frozen=True)
class FmuDeclaration:
    """Everything an FMU of this project is: the modelDescription.xml is generated from it."""

    model_name: str
    description: str
    #: the model's own step (fixedInternalStepSize); communication steps are whole multiples of it
    internal_step: float
    variables: tuple[Variable, ...]
    #: the class connecting the values to the model (see the module documentation)
    adapter: Callable
    #: simulated time of the default experiment
    stop_time: float = 1.0
    version: str = "0.2.0"
    author: str = "aaa-cosim"
    extra_units: tuple[str, ...] = field(default=())
    #: the FMU's limit table: variable name -> its plausible range (one place for each limit)
    limits: dict[str, Limit] = field(default_factory=dict)
    #: structural parameter -> the coupling rule its value follows (another FMU's size it must equal),
    #: quoted when an importer gives an array it sizes the wrong number of values
    size_rules: dict[str, str] = field(default_factory=dict)
    #: the most internal steps one fmi3DoStep may run: a C importer cannot interrupt a call, so
    #: one that would take minutes is refused (with this number) instead of started
    max_steps_per_call: int = 100_000
    #: whether fmi3GetFMUState can save the model (its adapter's attributes survive ``copy.deepcopy``);
    #: False: canGetAndSetFMUState and canSerializeFMUState are false, and a call is refused saying why
    saves_state: bool = True

    def __post_init__(self):
        names = {v.name for v in self.variables} | {"internal_step"}
        unknown = sorted(set(self.limits) - names)
        if unknown:
            raise ValueError(f"{self.model_name}: limits for undeclared variables {unknown}")
        structural_names = {v.name for v in self.variables if v.causality == "structuralParameter"}
        unknown = sorted(set(self.size_rules) - structural_names)
        if unknown:
            raise ValueError(f"{self.model_name}: size rules for {unknown}, which are no structural parameters")

    def all_variables(self) -> tuple[Variable, ...]:
        """The declared variables after the two every FMU has: ``time`` and ``internal_step``,
        each with its limit from the table."""
        basics = (
            Variable("time", "Float64", "independent", "continuous", None, "s", "simulation time"),
            Variable("internal_step", "Float64", "parameter", "fixed", float(self.internal_step), "s",
                     "the model's internal step; communication steps must be whole multiples of it",
                     limit=INTERNAL_STEP_LIMIT),
        )
        return basics + tuple(replace(v, limit=self.limits[v.name]) if v.name in self.limits else v
                              for v in self.variables)


#: Every FMU's internal step: fmi3DoStep runs h / internal_step model steps in one call.
INTERNAL_STEP_LIMIT = Limit(1e-6, 10.0, "below 1 us a step costs less than the FMI call around it; above 10 s "
                                        "no model of this project is meant to step")


def output_publisher(variables, record_type, written_in_place=()) -> Callable[[Any, Any], None]:
    """``publish(values, record)``: copies into the FMU, after each step, every declared output that
    is a field of the model's output record ``record_type`` (a dataclass), except those the model
    writes into the FMU's buffers itself (``written_in_place``). A declared output that neither
    covers raises here, when the FMU's package is imported (the build): an output is its declaration
    plus its field. The copy is one assignment per output, as written by hand (it runs at 1 kHz: a
    loop over the names costs 0.4 us more per step)."""
    fields = {f.name for f in dataclasses_fields(record_type)}
    outputs = [v.name for v in variables if v.causality == "output"]
    missing = [name for name in outputs if name not in fields and name not in written_in_place]
    if missing:
        raise ValueError(f"outputs {missing} are declared but {record_type.__name__} has no such field and they "
                         "are not written in place: add the field to the model's outputs")
    names = [name for name in outputs if name in fields and name not in written_in_place]  # fields: identifiers
    body = "".join(f"    values.{name} = record.{name}\n" for name in names) or "    pass\n"
    namespace: dict = {}
    exec(f"def publish(values, record):\n{body}", namespace)
    publish = namespace["publish"]
    publish.__doc__ = f"Copy {', '.join(names) or 'nothing'} from the model's record into the FMU."
    return publish
