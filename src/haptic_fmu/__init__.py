"""Contact and haptics of the AAA co-simulation (the Contact FMU's model layer, no FMI).

Modules
- `aabb`, `ccd`: broad phase (AABB tree, swept boxes) and continuous collision detection.
- `penalty`: signed distance to a facet, penalty laws, barycentric force distribution.
- `local_model`: facets near the tool captured at each tissue frame, held or extrapolated.
- `passivity`: passivity observer and controller of the haptic port (Hannaford and Ryu 2002).
- `kernels`: numba kernels of the 1 kHz path (no validation).
- `model`: `ContactParameters`, `ContactModel` (the object the FMU wrapper delegates to).

Conventions (SI units)
- Surface triangles are local surface node ids, wound so that (b - a) x (c - a) is the OUTWARD
  normal n of the tissue (as `tissue_fmu.mesh.TetMesh.surface()` returns them).
- dist = (p - q) . n is the signed distance of a tool point to its nearest facet (q closest point);
  dist < 0 is penetration. Haptic force on the tool (law "linear", design eq. 5):
  F = -k dist n - b (v . n) n, v the tool velocity relative to the rendered surface; the tissue gets
  exactly -F split over the facet's vertices by the barycentric weights of q.
- Passivity energy E is the energy that flowed INTO the environment through the port
  (>= 0 while passive, < 0 when the rendering generated energy).

API
    params = ContactParameters(stiffness=500.0, damping=0.1, penalty_law="linear",
                               penalty_length=1e-3, detection="continuous", interpolation="linear",
                               local_model="extrapolate", tool="centerline", tool_radius=0.001,
                               passivity_controller=False, passivity_max_damping=20.0,
                               margin=0.003, frame_period=1/30).validate()
    model = ContactModel(surface_triangles, n_surface, n_tool, params)
    model.set_tissue_frame(t, positions, velocities)        # ~30 Hz, (n_surface,3) or flat
    out = model.step(t, dt, tool_positions, tool_velocities=None)   # ~1 kHz, evaluated at t + dt
    out.tool_force (3,), out.tip_force (3,), out.tissue_contact_force (n_surface,3),
    out.node_forces (n_tool,3), out.penetration_depth, out.contact_count, out.contact_energy,
    out.passivity_energy        # arrays are the model's buffers, overwritten by the next step
    state = model.get_state(); model.set_state(state)           # rollback (deep copies)
    model.inside, model.contact_faces, model.ccd_hits, model.local_refreshes   # diagnostics
Invalid parameters raise `ContactParameterError`, invalid run-time inputs `ContactInputError`
(both ValueError) naming the field and the fix.
"""
from .local_model import LocalModel
from .model import (ContactInputError, ContactModel, ContactOutputs, ContactParameterError,
                    ContactParameters, parameters_from_dict)
from .passivity import PassiveRenderer, PassivityObserver, controller_damping
from .penalty import PENALTY_LAWS, facet_contact, normal_force, penalty_energy

__all__ = [
    "ContactInputError", "ContactModel", "ContactOutputs", "ContactParameterError", "ContactParameters",
    "LocalModel", "PENALTY_LAWS", "PassiveRenderer", "PassivityObserver", "controller_damping",
    "facet_contact", "normal_force", "parameters_from_dict", "penalty_energy",
]
