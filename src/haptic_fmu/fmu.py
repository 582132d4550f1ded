"""The Contact FMU: its interface, declared once, and the glue to :class:`haptic_fmu.model.ContactModel`.

Ports follow docs/design.md section 4. The tissue surface comes from the Tissue FMU: its topology
(``surface_triangles``, local surface-node ids) is a fixed parameter, and a new tissue frame is
taken exactly when the input ``tissue_frame`` changes (connect it to Tissue's ``frame``), however
often an importer sets the other inputs; between frames the 1 kHz loop renders the local model.

Start values (array sizes, triangles, rest positions) are those of the default AAA mesh; the
build writes them to ``default_tissue_surface.npz`` beside this file from the Tissue package,
so this package never imports the Tissue package.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ._coupling import TOOL_POINTS, rule, size_rules
from ._fmi import FmuDeclaration, Limit, input_port, output, output_publisher, parameter, structural
from .model import ContactModel, ContactOutputs, ContactParameters
from .rendering import LOCAL_POLICIES

DEFAULT_SURFACE_FILE = Path(__file__).resolve().parent / "default_tissue_surface.npz"

_defaults = ContactParameters()

#: The plausible range of every number an importer gives this FMU, and why (docs/design.md section 7:
#: haptic devices render at most 5000 N/m and 12 N; the device's own limit is max_force). Values
#: outside are refused (fmi3Error naming the variable, the value and this range) instead of
#: rendering an absurd force.
LIMITS = {
    "stiffness": Limit(1e-3, 1e6, "devices render up to 5000 N/m and tissue penalties up to about 1e5 N/m; 1e6 N/m "
                                  "pushes 1 kN back for 1 mm of penetration"),
    "damping": Limit(0.0, 1e4, "the wall damping is 0 to about 10 N s/m; 1e4 N s/m brakes a 1 mm/s motion with 10 N"),
    "penalty_length": Limit(1e-6, 0.1, "the non-linear laws' length scale is micrometres to centimetres"),
    "tool_radius": Limit(0.0, 0.05, "a catheter is 0.3-4 mm in radius; a 5 cm tool fills the aorta"),
    "margin": Limit(1e-6, 0.5, "the broad-phase margin exceeds the deepest penetration (millimetres); 0.5 m makes "
                               "every triangle a candidate"),
    "passivity_max_damping": Limit(1e-6, 1e4, "the passivity controller's damping stays below 2 m/T (about 20 N s/m "
                                              "for a 10 g device at 1 kHz)"),
    # device.py: the PHANTOM Desktop's 7.9 N by default; a study of the contact alone may lift the limits out of reach
    "max_force": Limit(0.01, 1000.0, "haptic devices exert 3-40 N (Touch 3.3 N, PHANTOM Desktop 7.9 N, Premium 3.0 "
                                     "22 N); below 10 mN nothing is felt; up to 1 kN to study the contact unlimited"),
    "max_force_rate": Limit(1.0, 1e7, "10 N per 1 ms step by default, twice a 10 kN/m wall under a 0.5 m/s hand; below "
                                      "1 N/s a contact force takes seconds to build; 1e7 N/s (10 kN per step) limits "
                                      "nothing, to study the contact unlimited"),
    "passivity_cycle_tolerance": Limit(0.0, 1.0, "the share of its exchanged energy a contact cycle may create: 0 "
                                                 "reports all but round-off, 1 reports nothing (a cycle cannot "
                                                 "create more than it exchanged)"),
    "compliance_force_lag": Limit(1, 1000, "frames between a haptic interval and the tissue frame showing its force: "
                                           "2 with a Jacobi connection and an average"),
    "n_surface_nodes": Limit(3, 2_000_000, "surface nodes of a tissue mesh the Tissue FMU builds"),
    "n_surface_triangles": Limit(1, 4_000_000, "surface triangles of a tissue mesh the Tissue FMU builds"),
    "n_tool_points": Limit(1, 10_000, f"points of a catheter centerline ({TOOL_POINTS} by default) or 1 for a probe"),
    "max_patch_nodes": Limit(1, 256, "the compliance block is (3 n)^2 values solved by Tissue each frame"),
    "tissue_positions": Limit(-100.0, 100.0, "positions of a body's tissue lie within 100 m of the origin"),
    "tissue_velocities": Limit(-1e3, 1e3, "tissue moves at centimetres per second; 1 km/s is a diverged input"),
    # Tissue's softest accepted wall (young_modulus 100 Pa, no viscosity) yields 10 m/N over a 30 Hz
    # frame on the default mesh (its nodes' inertia bounds W, not the elasticity): this range must
    # hold every W a Tissue within its own limits sends (tested across the two tables)
    "compliance": Limit(-1e4, 1e4, "the softest wall Tissue accepts yields about 10 m/N over a 30 Hz frame; "
                                   "beyond 1e4 m/N the connection or the unit is broken"),
    "tool_positions": Limit(-100.0, 100.0, "tool points lie within 100 m of the origin"),
    "tool_velocities": Limit(-1e3, 1e3, "a hand moves a tool at most a few metres per second; 1 km/s is a broken "
                                        "input"),
}
FLOAT_PARAMETERS = [
    ("stiffness", "N/m", "penalty stiffness k"),
    ("damping", "N.s/m", "penalty damping b"),
    ("penalty_length", "m", "length scale d0 of the non-linear penalty laws"),
    ("tool_radius", "m", "radius of the catheter capsules (tool = centerline)"),
    ("margin", "m", "broad-phase margin of the local model"),
    ("passivity_max_damping", "N.s/m", "cap of the passivity controller's damping"),
    ("max_force", "N", "the haptic device's maximum force: tool_force never exceeds it (force_limited says when it "
                       "engages); default the PHANTOM Desktop / Touch X's 7.9 N"),
    ("max_force_rate", "N/s", "the fastest change of tool_force between samples (|F(j) - F(j-1)| <= rate x step)"),
    ("passivity_cycle_tolerance", None, "the share of its exchanged energy a contact cycle may create before the "
                                        "passivity observer reports it active (active_cycles)"),
]
STRING_PARAMETERS = [
    ("penalty_law", "linear, quadratic or hunt_crossley"),
    ("detection", "continuous or discrete"),
    ("interpolation", "tissue trajectories between frames for CCD: linear or cubic"),
    ("local_model", "the wall between tissue frames: " + ", ".join(LOCAL_POLICIES)),
    ("tool", "centerline (catheter capsules) or probe (one device point)"),
    ("compliance_free_motion", "the wall's free motion between frames with the compliance model: hold or "
                               "extrapolate"),
]


def _default_surface() -> tuple[np.ndarray, np.ndarray]:
    """Triangles and rest positions of the default tissue surface (one triangle if none shipped)."""
    if DEFAULT_SURFACE_FILE.exists():
        data = np.load(DEFAULT_SURFACE_FILE)
        return data["triangles"].astype(np.int32), data["positions"].astype(np.float64)
    return np.array([[0, 1, 2]], dtype=np.int32), np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])


# Read once at import: later instances in the same process may outlive the extraction folder.
DEFAULT_TRIANGLES, DEFAULT_POSITIONS = _default_surface()
PER_NODE, PER_TOOL = ("n_surface_nodes", 3), ("n_tool_points", 3)
PATCH_DOFS = ("max_patch_nodes", 3, "max_patch_nodes", 3)

VARIABLES = (
    *(parameter(name, float(getattr(_defaults, name)), text, unit) for name, unit, text in FLOAT_PARAMETERS),
    *(parameter(name, str(getattr(_defaults, name)), text) for name, text in STRING_PARAMETERS),
    parameter("passivity_controller", bool(_defaults.passivity_controller),
              "add damping when the passivity observer sees energy created"),
    parameter("energy_consistent", bool(_defaults.energy_consistent),
              "hold the penalty law's mean over the depths the tool's motion predicts for the step (a tap returns "
              "the energy it took); false: the law at the sampled depth (the classic sampled wall, which creates "
              "about K T / 2 v^2 per second)"),
    structural("n_surface_nodes", len(DEFAULT_POSITIONS), "tissue surface nodes (array size)"),
    structural("n_surface_triangles", len(DEFAULT_TRIANGLES), "tissue surface triangles (array size)"),
    structural("n_tool_points", TOOL_POINTS, "tool points: catheter centerline points, or 1 for a probe"),
    structural("max_patch_nodes", _defaults.max_patch_nodes,
               "most surface nodes the contact names for the wall's compliance (array size)"),
    parameter("compliance_force_lag", int(_defaults.compliance_force_lag),
              "frames between a haptic interval and the tissue frame computed under its mean force"),
    parameter("surface_triangles", DEFAULT_TRIANGLES, "tissue surface triangles (local surface-node ids, outward)",
              type="Int32", shape=("n_surface_triangles", 3)),
    input_port("tissue_positions", "tissue surface node positions (from Tissue)", "m", shape=PER_NODE,
               start=DEFAULT_POSITIONS),
    input_port("tissue_velocities", "tissue surface node velocities (from Tissue)", "m/s", shape=PER_NODE),
    input_port("tissue_frame", "tissue frame counter (from Tissue's frame): the tissue inputs are taken "
               "when it changes", type="Int32", start=0),
    input_port("compliance", "compliance W of the wall at the patch over the next tissue step (from Tissue): "
               "node-major (x, y, z) rows and columns of compliance_nodes; -1 slots ignored", "m/N",
               shape=PATCH_DOFS),
    input_port("compliance_nodes", "the surface nodes W was computed for (from Tissue), -1 padded",
               type="Int32", shape=("max_patch_nodes",), start=-1),
    input_port("tool_positions", "tool points (catheter centerline from Catheter, or the device probe)", "m",
               shape=PER_TOOL),
    input_port("tool_velocities", "tool point velocities (optional; differenced from positions when never set)",
               "m/s", shape=PER_TOOL),
    output("tool_force", "total force on the tool (device)", "N", shape=(3,)),
    output("tip_force", "force on the last tool point (catheter tip)", "N", shape=(3,)),
    output("tip_stiffness", "stiffness of tip_force against the tip's motion, -d tip_force / d tip (3x3, to "
           "Catheter: its passive bend is integrated against it); for a tip near the wall that carries no force, "
           "the stiffness it will meet on touching", "N/m", shape=(3, 3)),
    output("tip_gap", "clearance of a catheter tip near the wall that carries no force, along the normal it will "
           "meet (to Catheter, with tip_stiffness: the passive bend meets the wall in the step it reaches it); "
           "zeros in contact or far from the wall", "m", shape=(3,)),
    output("tissue_contact_force", "contact forces on the tissue surface nodes (to Tissue)", "N", shape=PER_NODE),
    output("penetration_depth", "largest interpenetration", "m"),
    output("contact_energy", "penalty potential energy", "J"),
    output("passivity_energy", "energy into the environment through the haptic port (>= 0: passive)", "J"),
    output("contact_count", "number of active contacts", type="Int32"),
    output("force_limited", "the device limit (max_force, max_force_rate) shaped tool_force at this step; tip_force "
           "and tissue_contact_force keep the physical contact force", type="Boolean"),
    output("force_limited_steps", "internal steps whose tool_force was limited, since the start", type="Int32"),
    output("contact_cycles", "contact cycles completed (a touch and its release)", type="Int32"),
    output("active_cycles", "contact cycles that returned more energy than they took (beyond "
           "passivity_cycle_tolerance of the energy they exchanged and round-off)", type="Int32"),
    output("last_cycle_energy", "energy into the environment over the last completed contact cycle, taken minus "
           "returned (>= 0: passive)", "J"),
    output("patch_nodes", "surface nodes in or near the contact whose compliance the wall model needs (to "
           "Tissue), ascending, -1 padded", type="Int32", shape=("max_patch_nodes",)),
)


#: The outputs copied from the model's record after each step (the arrays it writes in place).
publish_outputs = output_publisher(VARIABLES, ContactOutputs,
                                   written_in_place=("tool_force", "tip_force", "tissue_contact_force", "patch_nodes"))


class ContactFmu:
    """Builds the contact model from the parameters and steps it with the inputs."""

    def __init__(self, values):
        self.values = v = values
        params = ContactParameters(
            passivity_controller=bool(v.passivity_controller), energy_consistent=bool(v.energy_consistent),
            max_patch_nodes=v.max_patch_nodes, compliance_force_lag=v.compliance_force_lag,
            **{name: float(getattr(v, name)) for name, _, _ in FLOAT_PARAMETERS},
            **{name: str(getattr(v, name)) for name, _ in STRING_PARAMETERS},
        )
        default_sizes = (len(DEFAULT_POSITIONS), len(DEFAULT_TRIANGLES))
        sizes = (int(v.n_surface_nodes), int(v.n_surface_triangles))
        if not v.set_count("surface_triangles") and sizes != default_sizes:
            raise ValueError(f"surface_triangles was never set, but the surface is not the default mesh's "
                             f"({sizes[0]} nodes, {sizes[1]} triangles instead of {default_sizes[0]}, "
                             f"{default_sizes[1]}): set it to Tissue's surface_triangles; {rule('triangles')}")
        self.model = ContactModel(np.array(v.surface_triangles), int(v.n_surface_nodes), int(v.n_tool_points),
                                  params)
        self._take_frame(float(v.time))
        self.frame = int(v.tissue_frame)
        self.frame_time = float(v.time)
        self.model.write_outputs_into(v.tool_force, v.tip_force, v.tissue_contact_force, v.patch_nodes)

    def _take_frame(self, t: float) -> None:
        v = self.values
        nodes = v.compliance_nodes
        if (nodes >= 0).any():
            self.model.set_tissue_frame(t, v.tissue_positions, v.tissue_velocities, compliance=v.compliance,
                                        compliance_nodes=nodes)
        else:
            self.model.set_tissue_frame(t, v.tissue_positions, v.tissue_velocities)

    def step(self, t: float, dt: float) -> None:
        v, model = self.values, self.model
        frame = v.tissue_frame
        if frame != self.frame:
            if not t > self.frame_time:
                raise ValueError(f"tissue_frame changed from {self.frame} to {frame} at t = {t!r} s, before Contact "
                                 f"stepped past its frame of t = {self.frame_time!r} s; {rule('frame')}")
            self._take_frame(t)
            self.frame, self.frame_time = frame, t
        velocities = v.tool_velocities if v.set_count("tool_velocities") else None
        out = model.step(t, dt, v.tool_positions, velocities)
        # the model writes the arrays into the FMU's buffers; a model restored from an FMU state (a
        # copy) wrote this step into its own: bind it to the buffers again (they take this step's values)
        if out.tissue_contact_force is not v.tissue_contact_force:
            model.write_outputs_into(v.tool_force, v.tip_force, v.tissue_contact_force, v.patch_nodes)
        publish_outputs(v, out)


DECLARATION = FmuDeclaration(
    model_name="Contact",
    description="Continuous collision detection (AABB tree, spline trajectories), penalty response and penalty "
                "haptic rendering with a local model of the wall",
    internal_step=0.001,
    variables=VARIABLES,
    adapter=ContactFmu,
    limits=LIMITS,
    size_rules=size_rules("Contact"),
)
