"""A touch and release returns the energy it took: the energy-consistent hold, against the sampled law.

The port energy is computed here from the forces and positions the model returns, as a haptic
device experiences it: the force of sample j is held while the tool moves from x_j to x_j+1, so
the work into the environment is -sum F_j . (x_j+1 - x_j) (Hannaford and Ryu). A sampled penalty
wall (the law at the sampled depth) creates k (x_j+1 - x_j)^2 / 2 per step in both directions; the
energy-consistent hold (the law's mean over the predicted depths) creates nothing at constant
speed, to round-off.
"""
import numpy as np
import pytest

from haptic_fmu import penalty
from haptic_fmu.model import ContactModel, ContactParameters


def flat_wall(n=6, size=0.02):
    """A flat wall z <= 0 (normal +z), n x n nodes, 2 (n-1)^2 triangles."""
    x = np.linspace(-size / 2, size / 2, n)
    X, Y = np.meshgrid(x, x, indexing="ij")
    pos = np.stack([X.ravel(), Y.ravel(), np.zeros(n * n)], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    tri = np.array([t for i in range(n - 1) for j in range(n - 1) for t in (
        [idx[i, j], idx[i + 1, j], idx[i + 1, j + 1]], [idx[i, j], idx[i + 1, j + 1], idx[i, j + 1]])])
    return pos, tri


def tap_path(start, depth, speed, taps, dt=1e-3):
    """z of a probe tapping the wall: from `start` above it down past `depth` below and back at a
    constant speed (the turn is the only change of velocity), `taps` times."""
    down = np.arange(start, -depth, -speed * dt)
    return np.concatenate([np.tile(np.concatenate([down, down[::-1][1:-1]]), taps), [start]])


def port_work(forces, positions):
    """Work into the environment over each hold interval: -F_j . (x_j+1 - x_j)."""
    return -np.einsum("ij,ij->i", forces[:-1], np.diff(positions, axis=0))


def cycles(forces, work):
    """Per contact cycle (the samples with a nonzero force, each with the interval it is held
    over): (net energy into the environment, energy exchanged = sum |work|, sample range)."""
    active = np.any(forces[:-1] != 0.0, axis=1)
    found, start = [], None
    for j, on in enumerate(active):
        if on and start is None:
            start = j
        if not on and start is not None:
            found.append((work[start:j].sum(), np.abs(work[start:j]).sum(), (start, j)))
            start = None
    return found


def tap(model, z, x=0.0012, y=-0.0007):
    positions = np.stack([np.full_like(z, x), np.full_like(z, y), z], axis=1)
    forces = np.array([model.step(j * 1e-3, 1e-3, positions[j][None]).tool_force.copy() for j in range(len(z))])
    return forces, positions


@pytest.mark.parametrize("law", ["linear", "quadratic", "hunt_crossley"])
@pytest.mark.parametrize("speed", [0.013, 0.05])
def test_a_tap_returns_what_it_took_but_for_the_turn(law, speed):
    """Over every interval at constant speed the held force does exactly the potential's change
    (round-off), first touch and release included; only the turn, where the velocity changes and
    the prediction (the mean velocity of the last two steps) misses, leaves a second-order residual,
    at most k/2 sum |dz_j| |a_j - dz_j| (a_j the predicted step) for the linear law. The sampled law
    creates k (v T)^2 / 2 on every step in contact: 7-40x more on these taps."""
    pos, tri = flat_wall()
    k = 3000.0
    z = tap_path(0.0004, 0.0011, speed, taps=3)
    step = np.diff(z)
    predicted = np.concatenate([[0.0, step[0]], 0.5 * (step[1:-1] + step[:-2])])   # a_j, held over step[j]
    results = {}
    for consistent in (True, False):
        model = ContactModel(tri, len(pos), 1, ContactParameters(
            tool="probe", stiffness=k, damping=0.0, penalty_law=law, local_model="hold",
            energy_consistent=consistent))
        model.set_tissue_frame(0.0, pos, np.zeros_like(pos))
        forces, positions = tap(model, z)
        work = port_work(forces, positions)
        results[consistent] = (work, cycles(forces, work))
    work, found = results[True]
    assert len(found) == len(results[False][1]) == 3
    potential = np.array([penalty.penalty_energy(max(-x, 0.0), law, k) for x in z])
    steady = np.flatnonzero(np.abs(predicted - step) < 1e-12 * speed)
    exact = potential[steady + 1] - potential[steady]
    assert np.count_nonzero(exact) > 50
    np.testing.assert_allclose(work[steady], exact, rtol=1e-9, atol=1e-12 * np.abs(exact).max())
    # the law's steepest slope on the path (k for the linear law) bounds the residual of the turns
    slope = max((penalty.normal_force(d + 1e-9, 0.0, law, k) - penalty.normal_force(d, 0.0, law, k)) / 1e-9
                for d in np.linspace(1e-6, 0.0011, 50))
    for net, exchanged, (a, b) in found:
        assert exchanged > 1e-4
        turn = 0.5 * slope * np.sum(np.abs(step[a:b]) * np.abs(predicted[a:b] - step[a:b]))
        assert abs(net) <= turn * (1 + 1e-9) + 1e-12 * exchanged
    sampled = results[False][1]
    if law == "linear":
        for net, exchanged, (a, b) in sampled:
            assert net == pytest.approx(-0.5 * k * np.sum(step[a:b] ** 2), rel=0.05)
    for (net, _, _), (net_sampled, exchanged, _) in zip(found, sampled):
        assert net_sampled < -5 * abs(net) and net_sampled < -2e-3 * exchanged   # 5x more created, or worse


def test_a_tap_on_the_yielding_wall():
    """Against the compliance local model (the wall yields through W between frames) the hold is
    the mean of the series spring k / (1 + k w): a tap creates 20x less than the sampled law."""
    pos, tri = flat_wall()
    patch = np.sort(np.argsort(np.linalg.norm(pos[:, :2] - [0.0012, -0.0007], axis=1))[:16])
    W = 4e-4 * np.eye(3 * patch.size)               # 0.4 mm/N at the 16 nodes around the tap
    results = {}
    for consistent in (True, False):
        model = ContactModel(tri, len(pos), 1, ContactParameters(
            tool="probe", stiffness=2000.0, damping=0.0, local_model="compliance", energy_consistent=consistent))
        model.set_tissue_frame(0.0, pos, np.zeros_like(pos), compliance=W, compliance_nodes=patch,
                               applied_force=np.zeros((patch.size, 3)))
        forces, positions = tap(model, tap_path(0.0004, 0.0012, 0.03, taps=2))
        results[consistent] = cycles(forces, port_work(forces, positions))
    assert len(results[True]) == len(results[False]) == 2
    for (net, exchanged, _), (net_sampled, _, _) in zip(results[True], results[False]):
        assert exchanged > 1e-5
        assert abs(net) < 1e-3 * exchanged
        assert net_sampled < 20 * min(net, -1e-12) and net_sampled < -1e-2 * exchanged


def test_the_hold_changes_nothing_at_rest():
    """At rest the held force is the law itself: the settled forces of the scenes do not move."""
    pos, tri = flat_wall()
    forces = {}
    for consistent in (True, False):
        model = ContactModel(tri, len(pos), 1, ContactParameters(
            tool="probe", stiffness=1000.0, damping=0.3, local_model="hold", energy_consistent=consistent))
        model.set_tissue_frame(0.0, pos, np.zeros_like(pos))
        for j in range(3):
            out = model.step(j * 1e-3, 1e-3, [[0.001, 0.001, -0.0004]])
        forces[consistent] = out.tool_force.copy()
    np.testing.assert_array_equal(forces[True], forces[False])
    np.testing.assert_allclose(forces[True], [0.0, 0.0, 0.4], rtol=1e-12)
