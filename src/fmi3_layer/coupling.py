"""The coupling contract of the project's three FMUs, written once: what a master must do to compose them.

Each FMU package links this file as ``_coupling.py`` (an FMU carries only its own package). From
it come the sizes two FMUs must agree on (their structural parameters start equal), the
"Coupling" section of each FMU's ``documentation/index.html`` and its machine-readable twin
``documentation/coupling.json`` (the build, ``fmu_build/documentation.py``), the FMU reference
pages (``tools/fmu_reference.py``) and the messages with which an FMU refuses a broken rule
(each quotes the rule by its name here). ``tests/test_coupling_contract.py`` checks that the
default scene (``scenes/aaa_endovascular.toml``) wires the FMUs exactly as :data:`LINKS` says, and
``examples/fmpy_master.py`` composes the FMUs from this contract alone.

Plain Python data, no imports beyond the standard library: the names are the FMUs' model names
(``Tissue``, ``Contact``, ``Catheter``) and their variables.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

#: Catheter centerline points (its segments + 1): the tool points the Contact renders by default.
TOOL_POINTS = 31
#: The most surface nodes the Contact names for the wall's compliance: the patch the Tissue solves.
PATCH_NODES = 16

#: Each FMU's step in the contract: the communication step is its fixedInternalStepSize.
STEPS = {"Tissue": "1/30", "Contact": "1/1000", "Catheter": "1/1000"}


@dataclass(frozen=True)
class Link:
    """One connection: ``source`` (``FMU.variable`` or ``operator.<what>``) to ``target``."""

    source: str
    target: str
    #: how the consumer's input is made from the producer's samples: ``hold`` (the latest), ``average``
    #: (the mean of the samples in the consumer's window), ``parameter`` (once, in Initialization Mode)
    transition: str
    #: ``gauss-seidel``: the producer steps to the end of the consumer's step first; ``jacobi``: the
    #: consumer sees the producer's samples up to the start of its step (the two may step concurrently)
    ordering: str
    #: which value the consumer stepping ``[t, t + h]`` gets
    sees: str


LINKS = (
    Link("operator.insertion", "Catheter.insertion", "hold", "gauss-seidel",
         "the operator's value at t + h (the end of the step), set before fmi3DoStep(t, h)"),
    Link("operator.rotation", "Catheter.rotation", "hold", "gauss-seidel",
         "the operator's value at t + h (the end of the step), set before fmi3DoStep(t, h)"),
    Link("Catheter.centerline_positions", "Contact.tool_positions", "hold", "gauss-seidel",
         "the catheter's shape at t + h: Catheter steps first in each millisecond"),
    *(Link(f"Contact.{name}", f"Catheter.{name}", "hold", "jacobi",
           "Contact's output at t, from its step that ended at t (one step late: this breaks the algebraic loop)")
      for name in ("tip_force", "tip_stiffness", "tip_gap")),
    Link("Tissue.surface_triangles", "Contact.surface_triangles", "parameter", "",
         "Tissue's calculated parameter, read in Tissue's Initialization Mode and set on Contact before Contact "
         "leaves Initialization Mode (rule 'triangles')"),
    *(Link(f"Tissue.{source}", f"Contact.{target}", "hold", "jacobi",
           "the latest tissue frame finished at or before t, all from the same Tissue sample (rule 'frame')")
      for source, target in (("surface_positions", "tissue_positions"), ("surface_velocities", "tissue_velocities"),
                             ("compliance", "compliance"), ("compliance_nodes", "compliance_nodes"),
                             ("frame", "tissue_frame"))),
    Link("Contact.patch_nodes", "Tissue.patch_nodes", "hold", "jacobi",
         "Contact's latest output at or before t (the start of the tissue step)"),
    Link("Contact.tissue_contact_force", "Tissue.contact_force", "average", "jacobi",
         "the mean of Contact's outputs at its communication points in (t - 1/30 s, t] (rule 'average')"),
)


@dataclass(frozen=True)
class Agreement:
    """Structural parameters (``FMU.parameter``) of different FMUs that must be equal."""

    parameters: tuple[str, ...]
    default: int | None
    why: str

    def text(self) -> str:
        return f"{' = '.join(self.parameters)} ({self.why})"


AGREEMENTS = (
    Agreement(("Tissue.n_surface_nodes", "Contact.n_surface_nodes"), None,
              "the surface Tissue sends is the surface Contact renders; default: the default mesh's"),
    Agreement(("Tissue.n_surface_triangles", "Contact.n_surface_triangles"), None,
              "the triangles Tissue computes are the triangles Contact renders; default: the default mesh's"),
    Agreement(("Tissue.n_patch_nodes", "Contact.max_patch_nodes"), PATCH_NODES,
              "the patch Contact names is the patch Tissue solves the compliance for"),
    Agreement(("Catheter.n_tool_points", "Contact.n_tool_points"), TOOL_POINTS,
              "the centerline Catheter sends is the tool Contact renders"),
)

#: The rules a master follows, by name; an FMU that finds one broken quotes it ("coupling rule 'frame': ...").
RULES = {
    "time": "Communication points are n * step computed as a quotient (n / 30 s for Tissue, n / 1000 s for Contact "
            "and Catheter), never as a sum of steps; each FMU steps by exactly its fixed step.",
    "modes": "Set the structural parameters (array sizes, Tissue's mesh choice, Catheter's n_centerline_points) in "
             "Configuration Mode (fmi3EnterConfigurationMode right after fmi3InstantiateCoSimulation), the other "
             "parameters before or in Initialization Mode.",
    "initialization": "Leave Initialization Mode in the order Tissue, Catheter, Contact, each with the outputs of "
                      "those before it as its inputs at time 0: Catheter with the operator's values at 0 (its "
                      "inputs from Contact at their start values), Contact with Tissue's first frame (positions, "
                      "velocities, compliance, compliance_nodes, frame 0) and Catheter's initial centerline.",
    "triangles": "Contact.surface_triangles is Tissue.surface_triangles, set in Contact's Initialization Mode: "
                 "Contact's start values are the default mesh's, wrong for any other mesh.",
    "frame": "Tissue's step [T, T + 1/30 s] ends with a frame: its outputs surface_positions, surface_velocities, "
             "compliance, compliance_nodes and frame (the frame counter) are new. Hand them to Contact together, "
             "tissue_frame last, before Contact's first step that starts at or after T + 1/30 s; Contact takes "
             "them as a new frame exactly when tissue_frame changes. Frame 0 (from Initialization Mode) is "
             "Contact's initial frame: a new frame comes only after Contact has stepped past the last one.",
    "average": "Tissue's step [T, T + 1/30 s] takes contact_force = the mean of Contact's tissue_contact_force at "
               "Contact's communication points in (T - 1/30 s, T]: 33 or 34 samples (at T = 0 the output after "
               "initialization alone).",
    "force_lag": "Contact.compliance_force_lag is the number of frames between the haptic interval whose mean "
                 "force Tissue applied and the frame computed under it: 2 for the schedule of these links (force "
                 "averaged over the interval before the tissue step, frame seen after it).",
}


def contract_of(model_name: str) -> dict:
    """The part of the contract that concerns one FMU, JSON-able (``documentation/coupling.json``)."""
    def mine(name: str) -> bool:
        return name.split(".", 1)[0] == model_name

    return {
        "format": "aaa-cosim coupling contract 1",
        "fmu": model_name,
        "steps": dict(STEPS),
        "inputs": [asdict(link) for link in LINKS if mine(link.target)],
        "outputs": [asdict(link) for link in LINKS if mine(link.source)],
        "agreements": [{"parameters": list(a.parameters), "default": a.default, "why": a.why}
                       for a in AGREEMENTS if any(mine(p) for p in a.parameters)],
        "rules": dict(RULES),
    }


def size_rules(model_name: str) -> dict[str, str]:
    """Structural parameter of ``model_name`` -> the agreement it is part of, as a refusal quotes it
    (``FmuDeclaration.size_rules``)."""
    return {parameter.split(".", 1)[1]: f"coupling rule 'sizes': {agreement.text()}"
            for agreement in AGREEMENTS for parameter in agreement.parameters
            if parameter.split(".", 1)[0] == model_name}


def rule(name: str) -> str:
    """A rule as a refusal quotes it."""
    return f"coupling rule '{name}': {RULES[name]}"
