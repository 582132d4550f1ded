"""Contact and haptics of the AAA co-simulation (the Contact FMU's model layer, no FMI).

Modules, by role (as SOFA's collision pipeline and haptic rendering)
- broad phase: `aabb` (+ `aabb_kernels`): swept boxes, AABB tree with refit, `triangle_boxes`.
- narrow phase: `narrow_phase` (CCD candidates, closest facets and depths), `ccd` (+ `ccd_kernels`):
  conservative continuous collision detection; `geometry`: the closest-point primitives.
- response: `penalty` (+ `penalty_kernels`): penalty laws, forces on the tool and the tissue.
- rendering: `rendering` (+ `rendering_kernels`): the local models between tissue frames,
  "compliance" (default: the wall yields through the compliance W from Tissue), "hold",
  "extrapolate"; the patch the contact names for W.
- passivity: `passivity`: passivity observer and controller of the haptic port (Hannaford and Ryu 2002).
- `model`: `ContactParameters`, `ContactModel` (the object the FMU wrapper delegates to);
  `ContactModel.step` runs the stages in that order.

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
                               local_model="compliance", tool="centerline", tool_radius=0.001,
                               passivity_controller=False, passivity_max_damping=20.0,
                               margin=0.003, frame_period=1/30, max_patch_nodes=16,
                               compliance_free_motion="hold", compliance_force_lag=2).validate()
    model = ContactModel(surface_triangles, n_surface, n_tool, params)
    model.set_tissue_frame(t, positions, velocities,        # ~30 Hz, (n_surface,3) or flat
                           compliance=W, compliance_nodes=ids,   # W (3p x 3p, m/N) of the ids the
                           applied_force=None)              # tissue used (last patch_nodes()), optional
    out = model.step(t, dt, tool_positions, tool_velocities=None)   # ~1 kHz, evaluated at t + dt
    out.tool_force (3,), out.tip_force (3,), out.tissue_contact_force (n_surface,3),
    out.node_forces (n_tool,3), out.penetration_depth, out.contact_count, out.contact_energy,
    out.passivity_energy        # arrays are the model's buffers, overwritten by the next step
    model.patch_nodes()          # (max_patch_nodes,) ids in or near the contact, ascending, -1 padded
    state = model.get_state(); model.set_state(state)           # rollback (deep copies)
    copy.deepcopy(model), pickle.loads(pickle.dumps(model))     # FMU state: continue bit-identically
    model.inside, model.contact_faces, model.ccd_hits, model.local_refreshes   # diagnostics
Invalid parameters raise `ContactParameterError`, invalid run-time inputs `ContactInputError`
(both ValueError) naming the field and the fix.
"""
from .model import (ContactInputError, ContactModel, ContactOutputs, ContactParameterError,
                    ContactParameters, parameters_from_dict)
from .passivity import PassiveRenderer
from .penalty import PENALTY_LAWS, normal_force, penalty_energy
from .rendering import ComplianceError, LocalModel, WallCompliance, check_compliance

__all__ = [
    "ComplianceError", "ContactInputError", "ContactModel", "ContactOutputs", "ContactParameterError",
    "ContactParameters", "LocalModel", "PENALTY_LAWS", "PassiveRenderer", "WallCompliance", "check_compliance",
    "normal_force", "parameters_from_dict", "penalty_energy",
]
