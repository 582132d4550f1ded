"""The Contact FMU: a thin FMI 3.0 Co-Simulation slave over :class:`haptic_fmu.model.ContactModel`.

Ports follow DESIGN.md section 4. The tissue surface comes from the Tissue FMU: its topology
(``surface_triangles``, local surface-node ids) is a fixed parameter set before initialization,
and a new tissue frame is taken whenever ``tissue_positions`` is set (the 30 Hz refresh of the
local model); between frames the 1 kHz loop holds or extrapolates the local model.

Start values (array sizes, triangles, rest positions) are those of the default AAA mesh; the
build writes them to ``default_tissue_surface.npz`` beside this file from the Tissue package,
so this package never imports the Tissue package.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from pythonfmu3 import (
    Boolean,
    Fmi3Causality,
    Fmi3Slave,
    Fmi3Variability,
    Int32,
    String,
)

from ._fmi_support import GuardedSlaveMixin
from .model import ContactModel, ContactParameters

C, V = Fmi3Causality, Fmi3Variability

DEFAULT_SURFACE_FILE = Path(__file__).resolve().parent / "default_tissue_surface.npz"

FLOAT_PARAMETERS = [
    ("stiffness", "N/m", "penalty stiffness k"),
    ("damping", "N.s/m", "penalty damping b"),
    ("penalty_length", "m", "length scale d0 of the non-linear penalty laws"),
    ("tool_radius", "m", "radius of the catheter capsules (tool = centerline)"),
    ("margin", "m", "broad-phase margin of the local model"),
    ("passivity_max_damping", "N.s/m", "cap of the passivity controller's damping"),
]
STRING_PARAMETERS = [
    ("penalty_law", "linear, quadratic or hunt_crossley"),
    ("detection", "continuous or discrete"),
    ("interpolation", "tissue trajectories between frames for CCD: linear or cubic"),
    ("local_model", "between tissue frames: hold or extrapolate"),
    ("tool", "centerline (catheter capsules) or probe (one device point)"),
]


def _default_surface() -> tuple[np.ndarray, np.ndarray]:
    """Triangles and rest positions of the default tissue surface (one triangle if none shipped)."""
    if DEFAULT_SURFACE_FILE.exists():
        data = np.load(DEFAULT_SURFACE_FILE)
        return data["triangles"].astype(np.int64), data["positions"].astype(np.float64)
    return np.array([[0, 1, 2]]), np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])


# Read once at import: later instances in the same process may outlive the extraction folder.
DEFAULT_TRIANGLES, DEFAULT_POSITIONS = _default_surface()


class ContactSlave(GuardedSlaveMixin, Fmi3Slave):
    """Continuous collision detection, penalty response and 1 kHz haptic rendering (Contact FMU)."""

    forwarded_loggers = (__name__.rsplit(".", 1)[0],)  # this package, under whatever name it was imported

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self._declare_basics("Continuous collision detection (AABB tree, spline trajectories), penalty "
                             "response and penalty haptic rendering with a local model", 0.001)
        self.model: ContactModel | None = None
        self._new_frame = False
        self._tool_velocities_given = False
        defaults = ContactParameters()
        fixed = dict(causality=C.parameter, variability=V.fixed)
        for name, _, _ in FLOAT_PARAMETERS:
            setattr(self, name, float(getattr(defaults, name)))
        self._register_scalars(FLOAT_PARAMETERS, C.parameter, V.fixed)
        for name, text in STRING_PARAMETERS:
            setattr(self, name, str(getattr(defaults, name)))
            self.register_variable(String(name, **fixed, description=text))
        self.passivity_controller = bool(defaults.passivity_controller)
        self.register_variable(Boolean("passivity_controller", **fixed,
                                       description="add damping when the passivity observer sees energy created"))

        triangles, rest = DEFAULT_TRIANGLES, DEFAULT_POSITIONS
        self._register_structural("n_surface_nodes", len(rest), "tissue surface nodes (array size)")
        self._register_structural("n_surface_triangles", len(triangles), "tissue surface triangles (array size)")
        self._register_structural("n_tool_points", 31, "tool points: catheter centerline points, or 1 for a probe")
        per_node, per_tool = ("n_surface_nodes", 3), ("n_tool_points", 3)
        self._register_array("surface_triangles", ("n_surface_triangles", 3), C.parameter,
                             "tissue surface triangles (local surface-node ids, outward)",
                             variability=V.fixed, dtype=np.int32)
        self.surface_triangles[...] = triangles
        self._register_array("tissue_positions", per_node, C.input,
                             "tissue surface node positions (from Tissue)", "m", on_set=self._mark_new_frame)
        self.tissue_positions[...] = rest
        self._register_array("tissue_velocities", per_node, C.input,
                             "tissue surface node velocities (from Tissue)", "m/s")
        self._register_array("tool_positions", per_tool, C.input,
                             "tool points (catheter centerline from Catheter, or the device probe)", "m")
        self._register_array("tool_velocities", per_tool, C.input,
                             "tool point velocities (optional; differenced from positions when never set)",
                             "m/s", on_set=self._mark_tool_velocities)
        self._register_array("tool_force", (3,), C.output, "total force on the tool (device)", "N")
        self._register_array("tip_force", (3,), C.output, "force on the last tool point (catheter tip)", "N")
        self._register_array("tissue_contact_force", per_node, C.output,
                             "contact forces on the tissue surface nodes (to Tissue)", "N")
        self.penetration_depth = 0.0
        self.contact_energy = 0.0
        self.passivity_energy = 0.0
        self.contact_count = 0
        self._register_scalars([
            ("penetration_depth", "m", "largest interpenetration"),
            ("contact_energy", "J", "penalty potential energy"),
            ("passivity_energy", "J", "energy into the environment through the haptic port (>= 0: passive)"),
        ], C.output, V.continuous)
        self.register_variable(Int32("contact_count", causality=C.output, variability=V.discrete,
                                     description="number of active contacts"))

    # -- setters with side effects ----------------------------------------------------------------
    def _mark_new_frame(self) -> None:
        self._new_frame = True

    def _mark_tool_velocities(self) -> None:
        self._tool_velocities_given = True

    # -- model delegation -----------------------------------------------------------------------
    def _initialize_model(self) -> None:
        params = ContactParameters(
            passivity_controller=bool(self.passivity_controller),
            **{name: float(getattr(self, name)) for name, _, _ in FLOAT_PARAMETERS},
            **{name: str(getattr(self, name)) for name, _ in STRING_PARAMETERS},
        )
        self.model = ContactModel(self.surface_triangles, int(self.n_surface_nodes), int(self.n_tool_points), params)
        self.model.set_tissue_frame(float(self.time), self.tissue_positions, self.tissue_velocities)
        self._new_frame = False

    def _step_model(self, t: float, dt: float) -> None:
        if self._new_frame:
            self.model.set_tissue_frame(t, self.tissue_positions, self.tissue_velocities)
            self._new_frame = False
        out = self.model.step(t, dt, self.tool_positions,
                              self.tool_velocities if self._tool_velocities_given else None)
        self.tool_force[...] = out.tool_force
        self.tip_force[...] = out.tip_force
        self.tissue_contact_force[...] = out.tissue_contact_force
        self.penetration_depth = float(out.penetration_depth)
        self.contact_count = int(out.contact_count)
        self.contact_energy = float(out.contact_energy)
        self.passivity_energy = float(out.passivity_energy)

    def _publish_outputs(self) -> None:
        """Outputs are written by ``_step_model``; before the first step they are zero."""
