"""FMU state of the Contact model: copy.deepcopy and pickle of a ContactModel that has stepped give
models that continue bit-identically (frames, compliance W and its force record, AABB tree, local
model, contact side memory, passivity energy, previous tool positions)."""
import copy
import math
import pickle

import numpy as np
import pytest

from haptic_fmu.model import ContactModel, ContactParameters
from test_haptic_compliance import SpringMassWall, probe_path
from test_haptic_model import facet_mid_direction, tube_surface


def _snapshot(model, out):
    return (out.tool_force.copy(), out.tip_force.copy(), out.tissue_contact_force.copy(), out.node_forces.copy(),
            out.penetration_depth, out.contact_count, out.contact_energy, out.passivity_energy,
            model.patch_nodes(), model.wall_displacement, model.contact_faces, model.inside,
            model._renderer.min_energy, model._renderer.last_alpha, model.ccd_hits, model.local_refreshes)


def _assert_same(a, b):
    for x, y in zip(a, b):
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y)
        else:
            assert x == y


class WallScene:
    """A probe pressed into the 30 Hz spring-mass wall (compliance from the wall's W)."""

    def __init__(self, policy):
        self.wall = SpringMassWall()
        self.h = 0.033
        self.inv = self.wall.solver(self.h)
        self.model = ContactModel(self.wall.tri, self.wall.n, 1, ContactParameters(
            tool="probe", stiffness=2000.0, local_model=policy, passivity_controller=True, margin=0.01,
            interpolation="cubic"))
        self.u = np.zeros((self.wall.n, 3))
        self.v = np.zeros((self.wall.n, 3))
        self.acc = np.zeros((self.wall.n, 3))
        self.pending = None

    def run(self, model, i0, i1, state):
        """Steps i0..i1-1 of `model`; the wall's own state is in `state` (copied by the caller)."""
        outs = []
        for i in range(i0, i1):
            t = i * 1e-3
            if i % 33 == 0:
                kwargs = {}
                if state["pending"] is not None:
                    f_used, ids = state["pending"]
                    state["u"], state["v"] = self.wall.step(state["u"], state["v"], f_used, self.h, self.inv)
                    if ids.size:
                        W = np.kron(self.h ** 2 * self.inv[np.ix_(ids, ids)], np.eye(3))
                        kwargs = dict(compliance=W, compliance_nodes=ids)   # applied force: the model's record
                model.set_tissue_frame(t, self.wall.rest + state["u"], state["v"], **kwargs)
                ids = model.patch_nodes()
                state["pending"] = (state["acc"] / 33, ids[ids >= 0])
                state["acc"] = np.zeros((self.wall.n, 3))
            out = model.step(t, 1e-3, probe_path(t + 1e-3) + [0.0, 0.0, 3e-4 * math.sin(60 * t)])
            state["acc"] = state["acc"] + out.tissue_contact_force
            outs.append(_snapshot(model, out))
        return outs


@pytest.mark.parametrize("policy", ["compliance", "hold", "extrapolate"])
@pytest.mark.parametrize("how", ["deepcopy", "pickle"])
def test_contact_model_copies_continue_bit_identically(policy, how):
    scene = WallScene(policy)
    state = dict(u=scene.u, v=scene.v, acc=scene.acc, pending=None)
    scene.run(scene.model, 0, 400, state)        # 12 frames: in contact, W in use, passivity active
    if policy == "compliance":
        assert scene.model.compliance.active and scene.model.patch_count > 0
    clone = copy.deepcopy(scene.model) if how == "deepcopy" else pickle.loads(pickle.dumps(scene.model))
    np.testing.assert_array_equal(clone.tree.node_lo, scene.model.tree.node_lo)
    state_copy = copy.deepcopy(state)
    first = scene.run(scene.model, 400, 700, state)
    again = scene.run(clone, 400, 700, state_copy)
    assert sum(f[5] for f in first) > 100                     # the continuation has contacts
    for a, b in zip(first, again):
        _assert_same(a, b)


def test_centerline_model_pickled_mid_run_continues_bit_identically():
    pos, tri = tube_surface(thickness=0.0015)
    model = ContactModel(tri, pos.shape[0], 4, ContactParameters(interpolation="cubic"))
    e, _ = facet_mid_direction(32, facet=2)

    def run(m, k0, k1):
        outs = []
        for k in range(k0, k1):
            if k % 33 == 0:
                m.set_tissue_frame(k * 1e-3, pos * (1 + 0.01 * math.sin(0.1 * k)), pos * 0.001 * math.cos(0.1 * k))
            s = np.linspace(0, 1, 4)[:, None]
            tool = (0.006 + (0.0045 + 0.001 * math.sin(0.3 * k)) * s) * e + s * [0, 0, 0.004]
            outs.append(_snapshot(m, m.step(k * 1e-3, 1e-3, tool)))
        return outs

    run(model, 0, 50)
    clone = pickle.loads(pickle.dumps(model))
    first, again = run(model, 50, 150), run(clone, 50, 150)
    assert sum(np.any(f[0] != 0) for f in first) > 10
    for a, b in zip(first, again):
        _assert_same(a, b)


def test_contact_model_unpickled_in_a_fresh_process_continues_bit_identically(tmp_path):
    """The serialized state restores in another interpreter (an FMU state read back after a restart):
    the unpickled model loads its kernels there and continues with the same outputs."""
    import subprocess
    import sys
    from pathlib import Path

    scene = WallScene("compliance")
    state = dict(u=scene.u, v=scene.v, acc=scene.acc, pending=None)
    scene.run(scene.model, 0, 300, state)
    (tmp_path / "state.pkl").write_bytes(pickle.dumps((scene.model, state)))
    first = scene.run(scene.model, 300, 400, state)
    np.save(tmp_path / "here.npy", np.array([np.concatenate([f[0], f[2].ravel(), [f[7]]]) for f in first]))
    tests = Path(__file__).resolve().parent
    script = f"""
import pickle, sys, numpy as np
sys.path[:0] = [{str(tests)!r}, {str(tests.parent / 'src')!r}]
from test_haptic_state import WallScene
model, state = pickle.loads(open({str(tmp_path / 'state.pkl')!r}, 'rb').read())
scene = WallScene("compliance")
outs = scene.run(model, 300, 400, state)
np.save({str(tmp_path / 'there.npy')!r}, np.array([np.concatenate([f[0], f[2].ravel(), [f[7]]]) for f in outs]))
"""
    subprocess.run([sys.executable, "-c", script], check=True, timeout=600)
    np.testing.assert_array_equal(np.load(tmp_path / "there.npy"), np.load(tmp_path / "here.npy"))


@pytest.mark.parametrize("policy", ["compliance", "hold"])
def test_outputs_written_into_bound_arrays_are_the_same_bits(policy):
    """write_outputs_into (an FMU's buffers): each step writes the same numbers into the caller's
    arrays, bound mid-run; a deepcopy of the bound model writes into arrays of its own."""
    scene, bound = WallScene(policy), WallScene(policy)
    state = dict(u=scene.u, v=scene.v, acc=scene.acc, pending=None)
    state_bound = copy.deepcopy(state)
    scene.run(scene.model, 0, 200, state)
    scene.run(bound.model, 0, 200, state_bound)  # the same steps: run() only uses the scene's wall
    model = bound.model
    tool_force, tip_force = np.full(3, np.nan), np.full(3, np.nan)
    tissue, patch = np.full((scene.wall.n, 3), np.nan), np.zeros(model.params.max_patch_nodes, np.int32)
    model.write_outputs_into(tool_force, tip_force, tissue, patch)
    np.testing.assert_array_equal(tool_force, scene.model._node_force.sum(axis=0))  # the current outputs
    np.testing.assert_array_equal(tissue, scene.model._tissue_force)
    np.testing.assert_array_equal(patch, scene.model.patch_nodes())
    clone = copy.deepcopy(model)
    state_clone = copy.deepcopy(state_bound)
    first = scene.run(scene.model, 200, 500, state)
    again = scene.run(model, 200, 500, state_bound)
    copied = scene.run(clone, 200, 500, state_clone)
    assert sum(f[5] for f in first) > 100
    for a, b, c in zip(first, again, copied):
        _assert_same(a, b)
        _assert_same(a, c)
    out = model.step(0.5, 1e-3, np.zeros((1, 3)))
    assert out.tool_force is tool_force and out.tip_force is tip_force and out.tissue_contact_force is tissue
    np.testing.assert_array_equal(patch, model.patch_nodes())
    assert clone.step(0.5, 1e-3, np.zeros((1, 3))).tissue_contact_force is not tissue
    with pytest.raises(ValueError, match="tissue_contact_force"):
        model.write_outputs_into(tool_force, tip_force, tissue[:-1], patch)
