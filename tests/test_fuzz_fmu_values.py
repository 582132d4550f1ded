"""Fuzzing the values an importer gives the project's FMUs (parameters, array sizes, enumerations,
mesh files, inputs), in fresh host processes: FMPy's low-level API and the C importer
(tests/fuzz_hosts.py). The FMUs are those of the build's table (tests/project.py); the variables
fuzzed are those each one declares (its model description), whichever kinds it has.

A case is a legal run of an FMU (PLAIN_RUNS, or one made from its model description) where some
parameters, sizes and inputs take values
from the edges: NaN, +-inf, +-1e300, 0, -1, each side of the variable's declared limit, huge and
negative counts, unknown enumeration strings, broken mesh files. The rule of issue 14: a clear
error or a correct result. Every case asserts:

- the host process survives, and no call takes longer than CALL_TIMEOUT (an excessive size or
  substep count is refused up front, not run for minutes);
- every call returns fmi3OK, fmi3Warning (a step) or fmi3Error, never Discard or Fatal; an error
  comes with a logged reason, and a refused set or a failed initialization names the variable;
- after an fmi3OK step, no Float64 output is NaN, infinite or absurd (beyond ABSURD in SI units:
  1e300 stiffness rendered 3e298 N before the limits).

Cases: the hypothesis profile decides (``ci``: 25 per FMU and host; ``--hypothesis-profile=long``: 1000).
"""
from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from fuzz_hosts import ERROR, OK, WARNING, ScriptHost, get_command, plain_run, ports, set_command
from project import FMU_NAMES

FMUS = FMU_NAMES
KINDS = ["fmpy", "c"]
#: No output of these FMUs means anything beyond this in SI units (metres, newtons, joules, radians).
ABSURD = 1e12
#: No call may take longer (the slowest legal call here, a Tissue build of the default mesh, takes ~2 s).
CALL_TIMEOUT = 60.0


@pytest.fixture(scope="module")
def hosts(fmus, c_host, tmp_path_factory):
    work = tmp_path_factory.mktemp("fuzz_values")
    made = {(kind, name): ScriptHost(kind, fmus[name], work / f"{kind}_{name}", c_host=c_host,
                                     call_timeout=CALL_TIMEOUT)
            for kind in KINDS for name in FMUS}
    yield made
    for host in made.values():
        host.close()
    print("fuzz_values: cases run", {f"{k}/{n}": h.cases_run for (k, n), h in made.items()})


@pytest.fixture(scope="module")
def mesh_files(tmp_path_factory):
    """Broken (and one good) tetrahedral mesh files for the Tissue's mesh_file."""
    import meshio

    from tissue_fmu import aaa_mesh

    folder = tmp_path_factory.mktemp("meshes")
    mesh = aaa_mesh(n_circumferential=8, n_axial=4, n_radial=1)
    good = folder / "coarse.vtu"
    meshio.write(good, meshio.Mesh(mesh.points, [("tetra", mesh.tets)]))
    data = good.read_bytes()
    files = {"good": good, "empty": folder / "empty.vtu", "garbage": folder / "garbage.vtu",
             "truncated": folder / "truncated.vtu", "triangles": folder / "triangles.vtu",
             "inverted": folder / "inverted.vtu"}
    files["empty"].write_bytes(b"")
    files["garbage"].write_bytes(bytes(range(256)) * 40)
    files["truncated"].write_bytes(data[: len(data) // 2])
    meshio.write(files["triangles"], meshio.Mesh(mesh.points, [("triangle", mesh.tets[:, :3])]))
    meshio.write(files["inverted"], meshio.Mesh(mesh.points, [("tetra", mesh.tets[:, [1, 0, 2, 3]])]))
    return {k: str(v) for k, v in files.items()} | {"missing": str(folder / "missing.vtu"), "folder": str(folder)}


# ---- values ------------------------------------------------------------------------------------------------
EDGES = [float("nan"), float("inf"), float("-inf"), 1e300, -1e300, 0.0, -1.0]


def float_values(port):
    values = list(EDGES)
    if port.maximum is not None:
        high, low = port.maximum, port.minimum
        values += [high, low, high * (1 + 1e-9) + 1e-300, low - abs(low) * 1e-9 - 1e-300]
        if low > 0:
            values.append(math.sqrt(low * high))
    return st.one_of(st.sampled_from(values), st.floats(allow_nan=False, allow_infinity=False))


def integer_values(port):
    values = [0, -1, 1, 2**31 - 1, -(2**31), 100000]
    if port.maximum is not None:
        values += [int(port.maximum), int(port.maximum) + 1, int(port.minimum), int(port.minimum) - 1]
    return st.sampled_from(values)


def size_values(port, plain):
    values = [0, 1, 2, 10**12, 2**63, int(plain)]
    if port.maximum is not None:
        values += [int(port.maximum), int(port.maximum) + 1]
    return st.sampled_from(values)


STRINGS = ["", "bogus", "linear", "explicit", "implicit", "probe", "off", "inlet,bogus", "\u00e9\u00e8 ", "x" * 5000]


def value_command(draw, port, plain_structural, mesh_files):
    if port.type == "f64":  # one element at the edge, the others at their start values
        starts = [float(x) for x in (port.start or "0").split()]
        array = starts * (port.size // len(starts)) if port.size % len(starts) == 0 else [0.0] * port.size
        array[draw(st.integers(0, port.size - 1))] = draw(float_values(port))
        return set_command(port, array)
    if port.type == "i32":
        return set_command(port, [draw(integer_values(port))] * port.size)
    if port.type == "u64":
        return set_command(port, [draw(size_values(port, plain_structural.get(port.name, port.start)))])
    if port.type == "bool":
        return set_command(port, [draw(st.sampled_from([0, 1]))])
    if port.name == "mesh_file":
        return set_command(port, [draw(st.sampled_from(sorted(mesh_files.values())))])
    return set_command(port, [draw(st.sampled_from(STRINGS))])


@st.composite
def value_cases(draw, run, p: dict, mesh_files: dict):
    """(commands, the variable each fuzzed command sets): a plain run with fuzzed values in it."""
    parameters = sorted((q for q in p.values() if q.causality == "parameter"), key=lambda q: q.vr)
    structural = sorted((q for q in p.values() if q.causality == "structuralParameter"), key=lambda q: q.vr)
    inputs = sorted((q for q in p.values() if q.causality == "input" and q.type == "f64"), key=lambda q: q.vr)
    fuzzed = {}

    def fuzz(port):
        command = value_command(draw, port, run.structural, mesh_files)
        fuzzed[command] = port.name
        return command

    commands = ["instantiate"]
    config = draw(st.lists(st.sampled_from(structural), max_size=1)) if structural else []
    commands += run.configure(p)[:-1] if run.structural else (["enter_config"] if config else [])
    commands += [fuzz(q) for q in config]
    commands += ["exit_config"] if (run.structural or config) else []
    commands += run.setup(p)
    if parameters:
        commands += [fuzz(q) for q in draw(st.lists(st.sampled_from(parameters), min_size=1, max_size=3))]
    commands += ["enter_init", "exit_init"]
    fuzzed_at = draw(st.integers(0, run.steps - 1))
    for k in range(run.steps):
        steps = run.step_commands(p, k)
        if k == fuzzed_at:
            fuzzed_inputs = draw(st.lists(st.sampled_from(inputs), max_size=2)) if inputs else []
            steps = steps[:-1] + [fuzz(q) for q in fuzzed_inputs] + steps[-1:]
        commands += steps
        commands += [get_command(q) for q in p.values() if q.causality == "output" and q.type == "f64"]
    return commands + ["terminate", "free"], fuzzed


def names_of(p) -> set[str]:
    return {q.name for q in p.values()}


def check(commands, fuzzed, answers, all_names) -> None:
    stepped_ok = False
    for command, answer in zip(commands, answers):
        errors = [m for s, m in answer.logs if s >= ERROR]
        assert answer.status in (OK, WARNING, ERROR), answer  # never Discard, Fatal
        if answer.status == ERROR:
            assert errors, f"fmi3Error without a reason: {answer}"
            sequence = any("illegal call sequence" in m for m in errors)  # after an earlier failure
            if command in fuzzed and not sequence:  # a refused value: the message names the variable
                assert any(fuzzed[command] in m for m in errors), (fuzzed[command], answer)
            elif command in ("exit_init", "exit_config") and not sequence:
                # the model could not be built, the arrays not sized: it says which variable
                assert any(any(n in m for n in all_names) for m in errors), answer
        elif answer.status == WARNING:
            assert command.startswith("step"), answer
        if command.startswith("step"):
            stepped_ok = answer.status in (OK, WARNING)
        if command.startswith("get f64") and answer.status == OK and stepped_ok:
            values = [float(x) for x in answer.values]
            assert all(math.isfinite(x) and abs(x) <= ABSURD for x in values), (answer, fuzzed)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("name", FMUS)
def test_edge_values_give_a_clear_error_or_a_correct_result(hosts, fmus, mesh_files, kind, name):
    run = plain_run(name, fmus[name])
    p = ports(fmus[name], run.structural)
    all_names = names_of(p) - {"time"}
    host = hosts[(kind, name)]

    @given(value_cases(run, p, mesh_files))
    def values_run(case):
        commands, fuzzed = case
        answers = host.run(commands)
        check(commands, fuzzed, answers, all_names)

    values_run()


# ---- the findings of issue 14, one by one (FMPy, this process) ------------------------------------------
@pytest.mark.parametrize("name, settings, when, words", [
    # silently absurd before the limit tables: 1e300 N/m rendered 3e298 N; an infinite tip force magnitude
    ("Contact", {"stiffness": 1e300}, "set", ["'stiffness'", "1e+300", "above the maximum", "[0.001, 1000000] N/m"]),
    ("Catheter", {"tip_force": [1e300, 0.0, 0.0]}, "set", ["'tip_force'", "above the maximum", "[-10000, 10000] N"]),
    ("Tissue", {"active_radius": float("nan")}, "set", ["'active_radius'", "NaN"]),
    ("Tissue", {"young_modulus": 1e300}, "set", ["'young_modulus'", "above the maximum", "[100, 10000000000] Pa"]),
    # a MemoryError for a resolution of 100000; minutes of meshing for a product of plausible ones
    ("Tissue", {"n_circumferential": 100000}, "init", ["n_circumferential = 100000", "above the maximum", "1024"]),
    ("Tissue", {"n_circumferential": 1024, "n_axial": 4096}, "init", ["MAX_ELEMENTS", "coarser mesh"]),
    # 104 s for 4 steps of automatic explicit substeps: refused up front, with the count and the way out
    ("Tissue", {"integrator": "explicit", "young_modulus": 1e9}, "init",
     ["substeps", "automatic substeps", "MAX_EXPLICIT_WORK", "implicit integrator"]),
    ("Catheter", {"internal_step": 1e-9}, "set", ["'internal_step'", "below the minimum", "[1e-06, 10] s"]),
])
def test_issue_findings_are_refused_early_with_the_variable_and_the_limit(fmus, name, settings, when, words):
    import time

    from fmu_harness import fmu_instance

    with fmu_instance(fmus[name]) as fmu:
        start = time.monotonic()
        items = list(settings.items())
        for variable, value in items[:-1]:
            fmu.set(variable, value)
        variable, value = items[-1]
        if when == "set":
            fmu.expect_error(lambda: fmu.set(variable, value), *words)
            fmu.initialize()  # nothing was set: the instance builds with its start values
        else:
            fmu.set(variable, value)
            fmu.expect_error(fmu.initialize, *words)
        assert time.monotonic() - start < 30.0
