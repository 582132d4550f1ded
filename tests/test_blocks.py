"""Built-in blocks of the orchestrator: sources (exact interpolation, CSV playback, rigid surfaces
checked against the real contact model) and the device plant (exact against the analytic solution,
energy balance, Colgate passivity of a sampled wall)."""
import math

import numpy as np
import pytest

from orchestration.blocks.registry import BLOCK_KINDS, REQUIRED, block_options, make_block
from orchestration.blocks.options import BlockConfigError
from orchestration.blocks.csv_source import CsvSource
from orchestration.blocks.plant import DevicePlant, exact_step_factors
from orchestration.errors import FmuCallError
from orchestration.blocks.sources import PiecewiseLinearSource
from orchestration.blocks.surfaces import RigidSurfaceSource

TIMES = [0.0, 0.5, 2.0, 3.0]
INSERTION = [0.0, 0.01, 0.05, 0.05]
POSITION = [[0.0, 0.0, 0.0], [0.1, -0.2, 0.3], [0.4, 0.4, -1.0], [1.0, 2.0, 3.0]]


def ramp_source(interpolation="linear"):
    return PiecewiseLinearSource("operator", TIMES, {"insertion": INSERTION, "position": POSITION},
                                 interpolation=interpolation, units={"insertion": "m"})


# ------------------------------------------------------------------------------------ piecewise
def test_piecewise_exact_at_knots_and_between():
    src = ramp_source()
    for t, ins, pos in zip(TIMES, INSERTION, POSITION):
        out = src.evaluate(t)
        assert out["insertion"].tolist() == [ins]  # exactly the knot value
        assert out["position"].tolist() == pos
    for i in range(len(TIMES) - 1):
        for w in (0.1, 0.25, 0.5, 0.9):
            t = TIMES[i] + w * (TIMES[i + 1] - TIMES[i])
            lam = (t - TIMES[i]) / (TIMES[i + 1] - TIMES[i])
            want = (1 - lam) * np.array(POSITION[i]) + lam * np.array(POSITION[i + 1])
            np.testing.assert_allclose(src.evaluate(t)["position"], want, rtol=0, atol=1e-15)
            want_ins = INSERTION[i] + lam * (INSERTION[i + 1] - INSERTION[i])
            assert src.evaluate(t)["insertion"][0] == pytest.approx(want_ins, rel=1e-15, abs=1e-18)


def test_piecewise_holds_outside_and_shapes():
    src = ramp_source()
    assert src.evaluate(-5.0)["position"].tolist() == POSITION[0]
    assert src.evaluate(1e9)["position"].tolist() == POSITION[-1]
    out = src.evaluate(1.0)
    assert out["insertion"].shape == (1,) and out["position"].shape == (3,)
    assert all(v.dtype == np.float64 for v in out.values())
    assert src.ports["insertion"].shape == () and src.ports["insertion"].unit == "m"
    assert src.ports["position"].shape == (3,) and src.ports["position"].causality == "output"
    # fresh copies: mutating a result does not change the source
    out["position"][:] = 99.0
    assert src.evaluate(1.0)["position"][0] != 99.0


def test_hold_mode_keeps_last_knot_value():
    src = ramp_source("hold")
    for i in range(len(TIMES) - 1):
        for t in (TIMES[i], TIMES[i] + 1e-9, 0.5 * (TIMES[i] + TIMES[i + 1]), np.nextafter(TIMES[i + 1], -1)):
            assert src.evaluate(t)["position"].tolist() == POSITION[i]
    assert src.evaluate(TIMES[-1])["insertion"].tolist() == [INSERTION[-1]]


def test_single_knot_is_constant():
    src = PiecewiseLinearSource("c", [1.0], {"f": [[1.0, 2.0, 3.0]]})
    for t in (-1.0, 1.0, 7.0):
        assert src.evaluate(t)["f"].tolist() == [1.0, 2.0, 3.0]


def test_evaluate_rejects_non_finite_time():
    with pytest.raises(ValueError, match="finite time"):
        ramp_source().evaluate(float("nan"))


@pytest.mark.parametrize("times, outputs, key, fragment", [
    ([0.0, 1.0, 1.0], {"a": [0, 1, 2]}, "times", "strictly increasing"),
    ([0.0, float("inf")], {"a": [0, 1]}, "times[1]", "finite"),
    ([], {"a": []}, "times", "at least one"),
    ("0 1", {"a": [0, 1]}, "times", "list of knot times"),
    ([0.0, 1.0], {"a": [0, 1, 2]}, "outputs.a", "one value per knot"),
    ([0.0, 1.0], {"a": [[0, 0, 0], [1, 1]]}, "outputs.a", "same number of components"),
    ([0.0, 1.0], {"a": [0, [1, 1]]}, "outputs.a", "same number of components"),
    ([0.0, 1.0], {"a": [0, float("nan")]}, "outputs.a[1]", "finite"),
    ([0.0, 1.0], {"a": [0, "x"]}, "outputs.a[1]", "finite"),
    ([0.0, 1.0], {}, "outputs", "non-empty"),
])
def test_piecewise_validation_names_the_key(times, outputs, key, fragment):
    with pytest.raises(BlockConfigError) as err:
        PiecewiseLinearSource("op", times, outputs)
    assert any(p.startswith(key) and fragment in p for p in err.value.problems), err.value.problems
    assert "op" in str(err.value)


def test_piecewise_bad_interpolation_and_units():
    with pytest.raises(BlockConfigError) as err:
        PiecewiseLinearSource("op", [0.0], {"a": [1.0]}, interpolation="cubic", units={"b": "m"})
    assert any(p.startswith("interpolation") and "'linear'" in p for p in err.value.problems)
    assert any(p.startswith("units") and "['b']" in p for p in err.value.problems)


# ------------------------------------------------------------------------------------ csv
def write_csv(path, times, insertion, position, extra_header=""):
    lines = ["time,ins,x,y,z" + extra_header]
    for t, i, p in zip(times, insertion, position):
        lines.append(",".join(repr(float(v)) for v in (t, i, *p)))
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("interpolation", ["linear", "hold"])
def test_csv_playback_equals_piecewise_source(tmp_path, interpolation):
    rng = np.random.default_rng(3)
    times = np.cumsum(rng.uniform(0.001, 0.1, 50))
    insertion = rng.normal(size=50)
    position = rng.normal(size=(50, 3))
    path = write_csv(tmp_path / "motion.csv", times, insertion, position)
    csv_src = CsvSource("rec", path, {"insertion": "ins", "position": ["x", "y", "z"]}, interpolation=interpolation)
    ref = PiecewiseLinearSource("ref", times.tolist(), {"insertion": insertion.tolist(),
                                                        "position": position.tolist()},
                                interpolation=interpolation)
    for t in np.concatenate([times, rng.uniform(times[0] - 1, times[-1] + 1, 200)]):
        a, b = csv_src.evaluate(t), ref.evaluate(t)
        assert a["insertion"].tolist() == b["insertion"].tolist()
        assert a["position"].tolist() == b["position"].tolist()
    assert csv_src.ports["insertion"].shape == () and csv_src.ports["position"].shape == (3,)


def csv_problems(tmp_path, text, columns=None, time_column="time"):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(BlockConfigError) as err:
        CsvSource("rec", path, columns or {"insertion": "ins"}, time_column=time_column)
    return err.value.problems


def test_csv_missing_file(tmp_path):
    with pytest.raises(BlockConfigError) as err:
        CsvSource("rec", tmp_path / "nope.csv", {"insertion": "ins"})
    assert err.value.problems[0].startswith("path") and "does not exist" in err.value.problems[0]


def test_csv_missing_columns(tmp_path):
    problems = csv_problems(tmp_path, "t,ins\n0,1\n", columns={"insertion": "ins", "p": ["x", "ins"]})
    assert any(p.startswith("time_column") and "'time'" in p and "['t', 'ins']" in p for p in problems)
    assert any(p.startswith("columns.p") and "['x']" in p for p in problems)


def test_csv_non_numeric_cell_names_line_and_column(tmp_path):
    problems = csv_problems(tmp_path, "time,ins\n0,1\n0.1,abc\n0.2,\n")
    assert any("line 3" in p and "'ins'" in p and "'abc'" in p for p in problems), problems
    assert any("line 4" in p and "'ins'" in p for p in problems), problems


def test_csv_non_monotonic_time(tmp_path):
    problems = csv_problems(tmp_path, "time,ins\n0,1\n0.2,1\n0.1,2\n")
    assert any("strictly increase" in p and "line 4" in p and "line 3" in p for p in problems), problems


def test_csv_ragged_row_and_empty(tmp_path):
    assert any("line 3 has 1 fields" in p for p in csv_problems(tmp_path, "time,ins\n0,1\n0.2\n"))
    assert any("no data rows" in p for p in csv_problems(tmp_path, "time,ins\n"))


# ------------------------------------------------------------------------------------ surfaces
def triangle_normals(pos, tri):
    return np.cross(pos[tri[:, 1]] - pos[tri[:, 0]], pos[tri[:, 2]] - pos[tri[:, 0]])


def test_plane_area_orientation_and_outputs():
    normal = np.array([1.0, 2.0, -0.5])
    src = RigidSurfaceSource("wall", "plane", center=[0.1, 0.2, 0.3], normal=normal.tolist(),
                             size=[0.08, 0.05], divisions=[7, 4])
    pos, tri = src.positions, src.triangle_ids
    assert src.n_nodes == 8 * 5 and src.n_triangles == 2 * 7 * 4
    cross = triangle_normals(pos, tri)
    areas = 0.5 * np.linalg.norm(cross, axis=1)
    assert areas.sum() == pytest.approx(0.08 * 0.05, rel=1e-13)
    unit = normal / np.linalg.norm(normal)
    np.testing.assert_allclose(cross / (2 * areas[:, None]), np.tile(unit, (len(tri), 1)), atol=1e-12)
    np.testing.assert_allclose((pos - [0.1, 0.2, 0.3]) @ unit, 0.0, atol=1e-15)  # all nodes on the plane
    out = src.evaluate(0.0)
    assert out["positions"].shape == (3 * src.n_nodes,) and not out["velocities"].any()
    assert out["triangles"].dtype == np.float64 and np.array_equal(out["triangles"].reshape(-1, 3), tri)
    assert src.ports["triangles"].type == "Int32" and src.ports["triangles"].shape == (src.n_triangles, 3)
    assert src.ports["positions"].shape == (src.n_nodes, 3)


@pytest.mark.parametrize("n_circumferential", [3, 8, 48])
def test_tube_area_against_analytic_and_orientation(n_circumferential):
    start, end, radius = np.array([0.01, -0.02, 0.0]), np.array([0.05, 0.03, 0.12]), 0.011
    src = RigidSurfaceSource("vessel", "tube", start=start.tolist(), end=end.tolist(), radius=radius,
                             n_circumferential=n_circumferential, n_axial=6)
    pos, tri = src.positions, src.triangle_ids
    length = np.linalg.norm(end - start)
    area = 0.5 * np.linalg.norm(triangle_normals(pos, tri), axis=1).sum()
    # the mesh is a prism over the inscribed regular polygon: perimeter n * 2 r sin(pi/n)
    chord = n_circumferential * 2 * radius * math.sin(math.pi / n_circumferential) * length
    assert area == pytest.approx(chord, rel=1e-12)
    exact = 2 * math.pi * radius * length
    x = math.pi / n_circumferential
    assert (exact - area) / exact == pytest.approx(1 - math.sin(x) / x, rel=1e-9)
    # nodes on the cylinder, every normal towards the axis
    axis = (end - start) / length
    rel = pos - start
    radial = rel - np.outer(rel @ axis, axis)
    np.testing.assert_allclose(np.linalg.norm(radial, axis=1), radius, rtol=1e-13)
    centroid = pos[tri].mean(axis=1) - start
    to_axis = -(centroid - np.outer(centroid @ axis, axis))
    cross = triangle_normals(pos, tri)
    cosine = np.einsum("ij,ij->i", cross, to_axis) / (np.linalg.norm(cross, axis=1) * np.linalg.norm(to_axis, axis=1))
    assert cosine.min() > 0.999 * math.cos(math.pi / n_circumferential) - 1e-12


def contact_force(src, p_outside, p_past):
    """Tool force of a probe moving from the allowed side to just past the surface."""
    from haptic_fmu.model import ContactModel, ContactParameters
    pos = src.positions
    model = ContactModel(src.triangle_ids, src.n_nodes, 1, ContactParameters(tool="probe"))
    model.set_tissue_frame(0.0, pos, np.zeros_like(pos))
    first = model.step(0.0, 1e-3, np.asarray(p_outside)[None]).tool_force.copy()
    second = model.step(1e-3, 1e-3, np.asarray(p_past)[None])
    return first, second.tool_force.copy(), second.penetration_depth


def test_plane_orientation_against_contact_model():
    normal = np.array([1.0, 1.0, 0.5]) / 1.5
    center = np.array([0.01, 0.0, -0.02])
    src = RigidSurfaceSource("wall", "plane", center=center.tolist(), normal=(1.5 * normal).tolist(),
                             size=0.1, divisions=5)
    on_plane = center + 0.003 * np.cross(normal, [0, 0, 1.0])  # a point of the plane, away from edges
    free, force, depth = contact_force(src, on_plane + 0.002 * normal, on_plane - 0.0005 * normal)
    assert not free.any()                       # on the allowed side: no force
    assert depth == pytest.approx(0.0005, rel=1e-9)
    assert force @ normal / np.linalg.norm(force) == pytest.approx(1.0, abs=1e-12)


def test_tube_orientation_against_contact_model():
    src = RigidSurfaceSource("vessel", "tube", start=[0, 0, 0], end=[0, 0, 0.1], radius=0.01,
                             n_circumferential=16, n_axial=5)
    # aim at the middle of a facet: its plane lies r cos(pi/n) from the axis
    theta = math.pi / 16 + 2 * math.pi / 16 * 3
    radial = np.array([math.cos(theta), math.sin(theta), 0.0])
    facet = 0.01 * math.cos(math.pi / 16)
    mid = np.array([0, 0, 0.05])
    free, force, depth = contact_force(src, mid + (facet - 0.002) * radial, mid + (facet + 0.0005) * radial)
    assert not free.any()                       # inside the tube: no force
    assert depth == pytest.approx(0.0005, rel=1e-9)
    assert force @ -radial / np.linalg.norm(force) == pytest.approx(1.0, abs=1e-12)  # back to the axis


@pytest.mark.parametrize("options, key", [
    (dict(normal=[0, 0, 0]), "normal"),
    (dict(normal=[0, 1]), "normal"),
    (dict(size=-1.0), "size"),
    (dict(divisions=0), "divisions"),
    (dict(center=[0, "a", 0]), "center"),
    (dict(radius=0.01), "radius"),              # a tube option given to a plane
])
def test_plane_validation_names_the_key(options, key):
    with pytest.raises(BlockConfigError) as err:
        RigidSurfaceSource("wall", "plane", **options)
    assert any(p.startswith(key) for p in err.value.problems), err.value.problems


@pytest.mark.parametrize("options, key", [
    (dict(radius=0.0), "radius"),
    (dict(n_circumferential=2), "n_circumferential"),
    (dict(n_axial=1.5), "n_axial"),
    (dict(start=[0, 0, 1], end=[0, 0, 1]), "end"),
    (dict(normal=[0, 0, 1]), "normal"),         # a plane option given to a tube
])
def test_tube_validation_names_the_key(options, key):
    with pytest.raises(BlockConfigError) as err:
        RigidSurfaceSource("vessel", "tube", **options)
    assert any(p.startswith(key) for p in err.value.problems), err.value.problems


def test_surface_bad_shape():
    with pytest.raises(BlockConfigError, match="shape must be one of"):
        RigidSurfaceSource("s", "sphere")


# ------------------------------------------------------------------------------------ device plant
OBSERVED = ["position", "velocity", "wall_energy", "operator_energy", "dissipated_energy", "kinetic_energy"]


def started_plant(**kwargs):
    plant = DevicePlant("device", **kwargs)
    plant.instantiate()
    plant.enter_initialization(0.0)
    plant.configure(["operator_force", "wall_force"], OBSERVED)
    plant.exit_initialization()
    return plant


def analytic(t, m, b, force, x0, v0):
    """m x'' + b x' = F, constant F (b > 0): x(t), v(t) in closed form, evaluated with 50-digit
    decimals so the reference has no cancellation even when b t / m is tiny."""
    from decimal import Decimal, localcontext
    with localcontext() as ctx:
        ctx.prec = 50
        t, m, b = Decimal(repr(t)), Decimal(repr(m)), Decimal(repr(b))
        tau = m / b
        decay = (-t / tau).exp()
        xs, vs = [], []
        for f, x_0, v_0 in zip(np.atleast_1d(force), np.atleast_1d(x0), np.atleast_1d(v0)):
            v_inf = Decimal(repr(float(f))) / b
            v_0, x_0 = Decimal(repr(float(v_0))), Decimal(repr(float(x_0)))
            xs.append(float(x_0 + v_inf * t + (v_0 - v_inf) * tau * (1 - decay)))
            vs.append(float(v_inf + (v_0 - v_inf) * decay))
    return np.array(xs), np.array(vs)


@pytest.mark.parametrize("m, b, step", [(0.1, 1.0, 1e-3), (0.05, 40.0, 2e-3), (2.0, 1e-5, 1e-3)])
def test_plant_exact_against_analytic_solution(m, b, step):
    x0, v0 = np.array([0.01, -0.02, 0.03]), np.array([0.5, 0.0, -1.0])
    force = np.array([1.0, -2.0, 0.5])
    plant = started_plant(mass=m, damping=b, step=step, initial_position=x0.tolist(), initial_velocity=v0.tolist())
    plant.set_inputs({"operator_force": 0.25 * force, "wall_force": 0.75 * force})
    for k in range(500):
        plant.start_step(k * step, step, {})
        out = plant.finish_step()
    x, v = analytic(500 * step, m, b, force, x0, v0)
    # 1e-12 relative to the motion (position change) and the velocity scale
    print(f"relative errors: position {np.abs(out['position'] - x).max() / np.abs(x - x0).max():.1e}, "
          f"velocity {np.abs(out['velocity'] - v).max() / np.abs(v).max():.1e}")
    assert np.abs(out["position"] - x).max() <= 1e-12 * np.abs(x - x0).max()
    assert np.abs(out["velocity"] - v).max() <= 1e-12 * np.abs(v).max()


def test_step_factors_continuous_across_series_switch():
    below, above = exact_step_factors(np.nextafter(0.5, 0)), exact_step_factors(0.5)
    np.testing.assert_allclose(below, above, rtol=1e-14)
    assert exact_step_factors(0.0) == pytest.approx((1.0, 0.5, 1.0, 1.0 / 3.0), rel=1e-15)


@pytest.mark.parametrize("mass, damping", [(0.2, 0.7), (0.01, 30.0), (0.2, 0.0)])  # b h / m: 0.0035, 3, 0
def test_energy_balance_closes_with_varying_forces(mass, damping):
    rng = np.random.default_rng(7)
    plant = started_plant(mass=mass, damping=damping, step=1e-3, initial_velocity=[0.1, -0.3, 0.2])
    start = plant.get_outputs()
    assert start["wall_energy"][0] == 0.0 and start["dissipated_energy"][0] == 0.0
    flow = 0.0  # sum of |work| per step: the scale of the round-off
    previous = start
    for k in range(1000):
        plant.start_step(k * 1e-3, 1e-3, {"operator_force": rng.normal(size=3),
                                          "wall_force": rng.normal(size=3) * (k % 3 == 0)})
        out = plant.finish_step()
        flow += sum(abs(out[n][0] - previous[n][0]) for n in ("wall_energy", "operator_energy", "dissipated_energy"))
        previous = out
    balance = (out["kinetic_energy"][0] - start["kinetic_energy"][0]
               - (out["operator_energy"][0] + out["wall_energy"][0] - out["dissipated_energy"][0]))
    assert out["dissipated_energy"][0] > 0 or damping == 0.0
    print(f"energy balance error {abs(balance) / flow:.2e} of the energy flow")
    assert abs(balance) <= 1e-12 * flow


def sampled_wall_run(damping, stiffness=1000.0, push=2.0, steps=3000, step=1e-3):
    """The operator pushes the device into a unilateral wall at x = 0 rendered as a sampled spring
    (force -K x_k held over the step). Returns the ideal-wall mechanical energy after each step
    (kinetic + wall spring potential - operator work potential) and the peak penetration per contact."""
    plant = started_plant(mass=0.1, damping=damping, step=step, initial_position=[-0.01, 0, 0])
    x = plant.get_outputs()["position"]
    energies, peaks, peak = [], [], 0.0
    for k in range(steps):
        wall = np.array([-stiffness * max(x[0], 0.0), 0.0, 0.0])
        plant.start_step(k * step, step, {"operator_force": np.array([push, 0, 0]), "wall_force": wall})
        out = plant.finish_step()
        x = out["position"]
        energies.append(out["kinetic_energy"][0] + 0.5 * stiffness * max(x[0], 0.0) ** 2 - push * x[0])
        if x[0] > 0:
            peak = max(peak, x[0])
        elif peak > 0:
            peaks.append(peak)
            peak = 0.0
    return np.array(energies), peaks


def test_colgate_sampled_wall_passive_when_device_damping_dominates():
    stiffness, step = 1000.0, 1e-3
    damping = 4 * stiffness * step / 2           # b_dev = 4 K T / 2: passive
    energies, _ = sampled_wall_run(damping, stiffness)
    start = -2.0 * -0.01                         # at rest at x = -0.01: only the operator potential
    assert energies.max() <= start
    assert np.all(np.diff(energies) <= 1e-15)    # never gains energy
    equilibrium = 0.5 * stiffness * (2.0 / stiffness) ** 2 - 2.0 * (2.0 / stiffness)
    assert energies[-1] == pytest.approx(equilibrium, rel=1e-6)  # settles on the wall


def test_colgate_sampled_wall_active_when_device_damping_too_small():
    stiffness, step = 1000.0, 1e-3
    damping = 0.1 * stiffness * step / 2         # b_dev = K T / 20: the sampled wall generates energy
    energies, peaks = sampled_wall_run(damping, stiffness)
    assert len(peaks) >= 10
    assert np.all(np.diff(peaks[:10]) > 0)       # each contact goes deeper than the last
    assert energies[-1] > 10 * energies[0]


def test_plant_protocol_and_errors():
    plant = DevicePlant("device", step=1e-3)
    assert plant.step_done()  # synchronous: nothing in flight
    with pytest.raises(FmuCallError):
        plant.set_inputs({"operator_force": np.zeros(3)})  # before instantiate
    plant.instantiate()
    plant.set_values({"mass": 0.2, "initial_position": [1.0, 2.0, 3.0]})
    with pytest.raises(FmuCallError, match="mass"):
        plant.set_values({"mass": -1.0})
    with pytest.raises(FmuCallError, match="settable"):
        plant.set_values({"stiffness": 1.0})
    plant.enter_initialization(0.5)
    plant.configure(["operator_force"], ["position", "kinetic_energy"])
    plant.set_inputs({"operator_force": np.array([0.2, 0.0, 0.0])})
    assert plant.get_outputs()["position"].tolist() == [1.0, 2.0, 3.0]
    values = plant.get_values(["mass", "operator_force", "initial_position"])
    assert values["mass"].tolist() == [0.2] and values["operator_force"].tolist() == [0.2, 0.0, 0.0]
    assert values["initial_position"].tolist() == [1.0, 2.0, 3.0]
    with pytest.raises(FmuCallError, match="no such ports"):
        plant.get_values(["force"])
    plant.exit_initialization()
    with pytest.raises(FmuCallError) as err:
        plant.start_step(0.5, 2e-3, {})
    assert err.value.call == "doStep" and "step" in err.value.reason and err.value.time == 0.5
    with pytest.raises(FmuCallError, match="plant is at t"):
        plant.start_step(0.7, 1e-3, {})
    with pytest.raises(FmuCallError, match="3 finite"):
        plant.start_step(0.5, 1e-3, {"operator_force": np.array([np.nan, 0, 0])})
    plant.start_step(0.5, 1e-3, {})
    out = plant.finish_step()
    assert set(out) == {"position", "kinetic_energy"}
    # a = F/m = 1 m/s^2 from rest: x = a h^2 / 2 - damping correction (b = 1, m = 0.2)
    x, _ = analytic(1e-3, 0.2, 1.0, 0.2, 1.0, 0.0)
    assert out["position"][0] == pytest.approx(x[0], rel=1e-14)
    plant.terminate()
    plant.terminate()  # idempotent


@pytest.mark.parametrize("kwargs, key", [
    (dict(mass=0.0), "mass"), (dict(damping=-0.1), "damping"), (dict(step=float("nan")), "step"),
    (dict(initial_position=[0, 0]), "initial_position"), (dict(initial_velocity=[0, 0, "x"]), "initial_velocity"),
    (dict(mass=True), "mass"),
])
def test_plant_validation_names_the_key(kwargs, key):
    with pytest.raises(BlockConfigError) as err:
        DevicePlant("device", **kwargs)
    assert any(p.startswith(key) for p in err.value.problems), err.value.problems


# ------------------------------------------------------------------------------------ factory
def test_factory_builds_every_kind(tmp_path):
    write_csv(tmp_path / "rec.csv", [0.0, 1.0], [0.0, 0.1], [[0, 0, 0], [1, 1, 1]])
    blocks = {
        "ramp": {"kind": "piecewise_linear", "times": [0.0, 1.0], "outputs": {"insertion": [0.0, 0.05]}},
        "rec": {"kind": "csv", "path": "rec.csv", "columns": {"insertion": "ins"}},
        "vessel": {"kind": "rigid_surface", "shape": "tube", "radius": 0.012},
        "device": {"kind": "device_plant", "mass": 0.2, "initial_position": [0, 0, 0.01]},
    }
    built = {name: make_block(name, table, tmp_path) for name, table in blocks.items()}
    assert isinstance(built["ramp"], PiecewiseLinearSource) and isinstance(built["rec"], CsvSource)
    assert built["rec"].evaluate(0.5)["insertion"][0] == pytest.approx(0.05, rel=1e-15)
    assert isinstance(built["vessel"], RigidSurfaceSource) and built["vessel"].options["radius"] == 0.012
    assert isinstance(built["device"], DevicePlant) and built["device"].step == 1e-3
    assert set(BLOCK_KINDS) == {"piecewise_linear", "csv", "rigid_surface", "device_plant"}


def test_factory_lists_every_problem_at_once(tmp_path):
    table = {"kind": "piecewise_linear", "outputs": {"a": [0, "x"]}, "interpolaton": "hold",
             "interpolation": "spline"}
    with pytest.raises(BlockConfigError) as err:
        make_block("ramp", table, tmp_path)
    problems = err.value.problems
    assert any("unknown key 'interpolaton'" in p and "'interpolation'" in p for p in problems)
    assert any("missing required key 'times'" in p for p in problems)
    assert any(p.startswith("outputs.a[1]") for p in problems)
    assert any(p.startswith("interpolation must be one of") for p in problems)
    assert len(problems) == 4


def test_factory_csv_problems_and_relative_path(tmp_path):
    with pytest.raises(BlockConfigError) as err:
        make_block("rec", {"kind": "csv", "path": "missing.csv", "columns": {"a": 3}, "hold": True}, tmp_path)
    problems = err.value.problems
    assert any("unknown key 'hold'" in p for p in problems)
    assert any(p.startswith("columns.a") for p in problems)
    with pytest.raises(BlockConfigError, match="missing.csv' does not exist"):
        make_block("rec", {"kind": "csv", "path": "missing.csv", "columns": {"a": "x"}}, tmp_path)


def test_factory_plant_and_surface_problems(tmp_path):
    with pytest.raises(BlockConfigError) as err:
        make_block("device", {"kind": "device_plant", "mass": "heavy", "damping": -1, "step": 0}, tmp_path)
    assert [p.split()[0] for p in err.value.problems] == ["mass", "damping", "step"]
    with pytest.raises(BlockConfigError) as err:
        make_block("wall", {"kind": "rigid_surface", "shape": "plane", "radius": 0.01, "size": 0}, tmp_path)
    assert any(p.startswith("radius applies to shape = 'tube'") for p in err.value.problems)
    assert any(p.startswith("size") for p in err.value.problems)


def test_factory_unknown_kind(tmp_path):
    for table in ({"kind": "sine"}, {}):
        with pytest.raises(BlockConfigError) as err:
            make_block("x", table, tmp_path)
        assert "kind must be one of" in err.value.problems[0] and "device_plant" in err.value.problems[0]


def test_block_options_documented_and_match_constructor_defaults():
    for kind in BLOCK_KINDS:
        options = block_options(kind)
        assert options and all(len(o) == 3 and isinstance(o[2], str) and o[2] for o in options)
    plant = DevicePlant("d")
    for name, default, _ in block_options("device_plant"):
        assert np.array_equal(np.atleast_1d(plant.ports[name].start), np.atleast_1d(default))
    assert dict((o[0], o[1]) for o in block_options("piecewise_linear"))["times"] is REQUIRED
    with pytest.raises(KeyError, match="kinds are"):
        block_options("sine")


def test_piecewise_linear_evaluate_on_floats_equals_the_array_formula_bitwise():
    """evaluate() computes on plain floats for speed; the values must be the array formula's, bit for bit."""
    from orchestration.blocks.sources import PiecewiseLinearSource

    rng = np.random.default_rng(7)
    times = np.cumsum(rng.uniform(0.01, 0.3, 12))
    source = PiecewiseLinearSource("s", times.tolist(), {"a": rng.normal(size=12).tolist(),
                                                         "b": rng.normal(size=(12, 3)).tolist()})
    for t in np.concatenate([rng.uniform(times[0] - 0.1, times[-1] + 0.1, 2000), times]):
        row = source._row(float(t))
        values = source.evaluate(float(t))
        assert values["a"].tobytes() == row[0:1].tobytes() and values["b"].tobytes() == row[1:4].tobytes()


@pytest.mark.parametrize("interpolation", ["linear", "hold"])
def test_evaluate_many_is_evaluate_bit_for_bit(interpolation):
    """The compiled loop fills a stretch's inputs with evaluate_many; the Python path calls evaluate."""
    src = PiecewiseLinearSource("op", [0.0, 0.2, 2.5, 4.0], {"insertion": [0.07, 0.07, 0.084, 0.084],
                                                            "force": [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0],
                                                                      [7.0, 8.0, 9.5], [0.1, 0.2, 0.3]]},
                                interpolation=interpolation)
    rng = np.random.default_rng(7)
    # random times, the knots themselves, before the first and after the last, and a 1 kHz grid of tick / base
    times = np.concatenate([rng.uniform(-1.0, 5.0, 2000), [0.0, -0.0, 0.2, 2.5, 4.0],
                            np.arange(0, 12000, dtype=np.int64) / 3000])
    many = src.evaluate_many(times)
    for k, t in enumerate(times):
        one = src.evaluate(float(t))
        for name in ("insertion", "force"):
            assert many[name][k].tobytes() == np.asarray(one[name]).reshape(-1).tobytes(), (name, t)
    surface = RigidSurfaceSource("wall", "plane", center=[0.0, 0.0, 0.0], normal=[0.0, 0.0, 1.0])
    rows = surface.evaluate_many(np.array([0.0, 0.5]))  # the generic one: evaluate at each time
    assert rows["positions"][1].tobytes() == surface.evaluate(0.5)["positions"].reshape(-1).tobytes()
