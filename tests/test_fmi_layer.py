"""The project's FMI 3.0 layer (src/fmi3_layer) against the standard's rules, on real built FMUs.

- Every FMI call in every state of the Co-Simulation state machine: legal calls succeed, illegal
  ones return fmi3Error with a logged reason and change nothing.
- Value references, counts, types and finiteness are checked on every get/set.
- Communication steps: whole multiples of the internal step, no gaps in time.
- FMU state: save, run on, restore, run again: bit-identical; the same through serialization
  into a fresh instance.
- A Python exception of any kind inside a call is fmi3Error; a KeyboardInterrupt is logged as
  "interrupted" and handed back to the host after the call (tested in fresh processes).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from fmpy.fmi1 import FMICallException

from fmu_harness import fmu_instance

H = 0.01  # the synthetic FMUs' internal step
STATES = ("Instantiated", "Configuration", "Initialization", "Step", "Terminated", "Error")


def _enter(fmu, state: str) -> None:
    """Bring a fresh Echo instance into ``state``."""
    slave = fmu.slave
    if state == "Configuration":
        slave.enterConfigurationMode()
    elif state == "Initialization":
        slave.enterInitializationMode()
    elif state in ("Step", "Terminated", "Error"):
        if state == "Error":
            fmu.set("fail_at", 0.0)
        fmu.initialize()
        if state == "Terminated":
            slave.terminate()
        elif state == "Error":
            with pytest.raises(FMICallException):
                slave.doStep(0.0, H)


def _calls(fmu):
    slave = fmu.slave
    return {
        "fmi3EnterInitializationMode": lambda: slave.enterInitializationMode(),
        "fmi3ExitInitializationMode": lambda: slave.exitInitializationMode(),
        "fmi3EnterConfigurationMode": lambda: slave.enterConfigurationMode(),
        "fmi3ExitConfigurationMode": lambda: slave.exitConfigurationMode(),
        "fmi3DoStep": lambda: slave.doStep(0.0, H),
        "fmi3Terminate": lambda: slave.terminate(),
        "fmi3Reset": lambda: slave.reset(),
        "fmi3GetFloat64 (output)": lambda: slave.getFloat64(fmu.vr("last_u")),
        "fmi3SetFloat64 (input)": lambda: slave.setFloat64(fmu.vr("u"), [1.0]),
        "fmi3SetBoolean (fixed parameter)": lambda: slave.setBoolean(fmu.vr("flag"), [True]),
        "fmi3SetUInt64 (structural parameter)": lambda: slave.setUInt64(fmu.vr("n_w"), [2]),
        "fmi3GetFMUState": lambda: slave.getFMUState(),
        "fmi3EnterEventMode": lambda: slave.enterEventMode(),
        "fmi3EnterStepMode": lambda: slave.enterStepMode(),
    }


#: Where each call is legal, from the FMI 3.0 Co-Simulation state machine (this FMU has no Event
#: Mode; structural parameters are fixed, so no Reconfiguration Mode).
LEGAL = {
    "fmi3EnterInitializationMode": {"Instantiated"},
    "fmi3ExitInitializationMode": {"Initialization"},
    "fmi3EnterConfigurationMode": {"Instantiated"},
    "fmi3ExitConfigurationMode": {"Configuration"},
    "fmi3DoStep": {"Step"},
    "fmi3Terminate": {"Step"},
    "fmi3Reset": set(STATES),
    "fmi3GetFloat64 (output)": {"Configuration", "Initialization", "Step", "Terminated", "Error"},
    "fmi3SetFloat64 (input)": {"Instantiated", "Initialization", "Step"},
    "fmi3SetBoolean (fixed parameter)": {"Instantiated", "Initialization"},
    "fmi3SetUInt64 (structural parameter)": {"Configuration"},
    "fmi3GetFMUState": {"Instantiated", "Initialization", "Step", "Terminated", "Error"},
    "fmi3EnterEventMode": set(),
    "fmi3EnterStepMode": set(),
}


@pytest.mark.parametrize("state", STATES)
def test_every_call_in_every_state(synthetic_fmus, state):
    for call in LEGAL:
        with fmu_instance(synthetic_fmus["Echo"]) as fmu:
            _enter(fmu, state)
            before = len(fmu.errors())
            if state in LEGAL[call]:
                _calls(fmu)[call]()
                assert len(fmu.errors()) == before, (call, state, fmu.errors())
            else:
                with pytest.raises(FMICallException) as info:
                    _calls(fmu)[call]()
                assert info.value.status == 3, (call, state)
                new = fmu.errors()[before:]
                assert new, f"{call} in {state} was refused without a reason"
                assert any(word in new[-1] for word in ("illegal call sequence", "cannot set", "not supported")), new
                if state == "Step":  # a refused call changed nothing: the instance steps on
                    fmu.slave.doStep(0.0, H)


def test_values_are_checked_on_every_get_and_set(synthetic_fmus):
    with fmu_instance(synthetic_fmus["Echo"]) as fmu:
        fmu.initialize()
        slave = fmu.slave
        for call, words in [
            (lambda: slave.getFloat64([9999]), "unknown value reference 9999"),
            (lambda: slave.getFloat64(fmu.vr("last_v"), nValues=2), "hold 3 value(s), but nValues = 2"),
            (lambda: slave.getFloat64(fmu.vr("last_k")), "is a Int32, not a Float64"),
            (lambda: slave.setFloat64(fmu.vr("last_u"), [1.0]), "it is an output"),
            (lambda: slave.setFloat64(fmu.vr("time"), [1.0]), "independent variable"),
            (lambda: slave.setFloat64(fmu.vr("u"), [float("nan")]), "only finite numbers"),
            (lambda: slave.setFloat64(fmu.vr("v"), [1.0, 2.0, 3.0, 4.0]), "hold 3 value(s), but nValues = 4"),
        ]:
            with pytest.raises(FMICallException):
                call()
            assert words in fmu.errors()[-1], (words, fmu.errors()[-1])
        fmu.slave.doStep(0.0, H)  # none of that changed the instance
        assert fmu.get("last_u") == 0.0 and fmu.errors()


def test_structural_parameters_resize_arrays_in_configuration_mode(synthetic_fmus):
    with fmu_instance(synthetic_fmus["Echo"]) as fmu:
        fmu.set("n_w", 5)  # the harness enters and leaves Configuration Mode
        fmu.initialize()
        fmu.slave.setFloat64(fmu.vr("w"), [1.0, 2.0, 3.0, 4.0, 5.0])
        fmu.slave.doStep(0.0, H)
        assert fmu.slave.getFloat64(fmu.vr("last_w"), nValues=5) == [1.0, 2.0, 3.0, 4.0, 5.0]


def test_communication_steps_are_whole_multiples_without_gaps(synthetic_fmus):
    with fmu_instance(synthetic_fmus["Echo"]) as fmu:
        fmu.initialize()
        fmu.set("u", 2.0)
        fmu.slave.doStep(0.0, 3 * H)  # three internal steps in one call
        assert fmu.get("integral_u") == pytest.approx(3 * 2.0 * H, rel=1e-15)
        assert fmu.get("last_t") == pytest.approx(2 * H, rel=1e-15)
        fmu.expect_step_error(3 * H, 1.5 * H, "whole multiple")
        fmu.expect_step_error(4 * H, H, "the FMU is at t = 0.03;")
        fmu.slave.doStep(3 * H, H)


#: Run in a fresh interpreter (the interrupt is handed back to the host: pytest must not receive it).
#: A step is interrupted (a model raising KeyboardInterrupt, or a real SIGINT sent to the process
#: while the FMU's Python code runs); the script prints what it saw, one fact a line.
INTERRUPT_SCRIPT = r"""
import os, signal, sys, threading
sys.path.insert(0, sys.argv[3])
from fmpy.fmi3 import fmi3Boolean, fmi3Float64
from fmu_harness import fmu_instance

fmu_path, how = sys.argv[1], sys.argv[2]
# Python raises a pending KeyboardInterrupt right after the call that returned (before its result
# is stored): to see the status, the first phase counts SIGINT handler runs instead (the first
# one, the real signal, raises inside the FMU; the handed-back one only counts).
handled = []

def counting_handler(signum, frame):
    handled.append(signum)
    if how == "sigint" and len(handled) == 1:
        raise KeyboardInterrupt

with fmu_instance(fmu_path) as fmu:
    h = float(fmu.md.coSimulation.fixedInternalStepSize)
    raw_step = fmu.slave._functions["fmi3DoStep"]  # the raw call: its status, no exception of FMPy's

    def step(k):
        refs = [fmi3Boolean(), fmi3Boolean(), fmi3Boolean(), fmi3Float64()]
        return raw_step(fmu.slave.component, k * h, h, True, *refs)

    def run_until_interrupted(retry_when_missed):
        if how == "model":
            fmu.set("interrupt_at", 2 * h)
        fmu.initialize()
        statuses = []
        for attempt in range(5):  # a SIGINT can land between two steps (in this script): then try again
            if how == "sigint":
                threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGINT)).start()
            try:
                while len(statuses) < 100000:
                    statuses.append(step(len(statuses)))
                    if statuses[-1] != 0:
                        return statuses
            except KeyboardInterrupt:
                if not retry_when_missed:
                    raise
                handled.clear()
                # it landed here, perhaps after a step had returned and before its status was kept:
                # go on from where the FMU is
                done = round(float(fmu.get("time")) / h)
                statuses[done:] = []
                statuses += [0] * (done - len(statuses))
        return statuses

    signal.signal(signal.SIGINT, counting_handler)
    statuses = run_until_interrupted(True)
    for _ in range(1000):  # the handed-back interrupt runs the handler at this loop's first check
        pass
    print("interrupted step status", statuses[-1], "after", len(statuses) - 1, "steps")
    print("handler runs", len(handled))
    print("logged", [m for m in fmu.errors() if "interrupted" in m][:1])
    print("next step status", step(len(statuses) - 1))
    print("next step reason", fmu.errors()[-1])
    # with Python's own handler the host stops: the KeyboardInterrupt reaches this script
    signal.signal(signal.SIGINT, signal.default_int_handler)
    handled.clear()
    fmu.slave.reset()
    host_interrupted = False
    try:
        run_until_interrupted(False)
        for _ in range(1000):
            pass
    except KeyboardInterrupt:
        host_interrupted = True
    print("host got KeyboardInterrupt", host_interrupted)
    fmu.slave.reset()
    if how == "model":
        fmu.set("interrupt_at", -1.0)
    fmu.initialize()
    print("after reset steps", [step(j) for j in range(3)])
print("exit normally")
"""


@pytest.mark.parametrize("how", ["model", "sigint"])
def test_an_interrupted_step_is_an_error_handed_back_to_the_host_in_a_fresh_process(how, synthetic_fmus,
                                                                                    tissue_fmu):
    """KeyboardInterrupt inside a step (raised by the model, or a real SIGINT while a Tissue step runs):
    fmi3Error logged as "interrupted", the host receives the KeyboardInterrupt after the call, the
    instance refuses further steps (Error mode) and runs again after fmi3Reset; the process exits
    normally."""
    import subprocess
    import sys
    from pathlib import Path

    fmu = synthetic_fmus["Faulty"] if how == "model" else tissue_fmu
    result = subprocess.run([sys.executable, "-c", INTERRUPT_SCRIPT, str(fmu), how, str(Path(__file__).parent)],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr[-2000:]
    out = result.stdout
    assert "interrupted step status 3 after" in out, out
    if how == "model":
        assert "after 2 steps" in out, out
    assert "handler runs " + ("1" if how == "model" else "2") in out, out  # the hand-back ran the handler
    assert "host got KeyboardInterrupt True" in out, out
    assert "fmi3DoStep: interrupted: a KeyboardInterrupt (SIGINT" in out, out
    assert "next step status 3" in out and "Error mode after:" in out, out
    assert "after reset steps [0, 0, 0]" in out and "exit normally" in out, out


def test_a_warning_logged_in_a_step_makes_that_step_fmi3warning(synthetic_fmus):
    from fmpy.fmi3 import fmi3Boolean, fmi3Float64

    with fmu_instance(synthetic_fmus["Faulty"]) as fmu:
        fmu.set("warn_at", H)
        fmu.initialize()
        do_step = fmu.slave._functions["fmi3DoStep"]  # the raw call: FMPy's doStep hides the status
        refs = [fmi3Boolean(), fmi3Boolean(), fmi3Boolean(), fmi3Float64()]
        statuses = [do_step(fmu.slave.component, k * H, H, True, *refs) for k in range(3)]
        assert statuses == [0, 1, 0]  # fmi3OK, fmi3Warning, fmi3OK
        assert fmu.get("y") == pytest.approx(3 * H) and refs[3].value == pytest.approx(3 * H)
        assert any(status == 1 and "requested warning at t = 0.01" in m for status, m in fmu.messages)


@pytest.mark.parametrize("index, kind, words", [(0, 0, "NaN"), (11, 1, "infinity"), (18, 2, "infinity")])
def test_a_non_finite_output_after_a_step_is_an_error(synthetic_fmus, index, kind, words):
    """The layer scans every Float64 output after each step (in blocks of 8 values, then the tail)."""
    with fmu_instance(synthetic_fmus["Faulty"]) as fmu:
        fmu.set("bad_at", 0.02)
        fmu.set("bad_index", index)
        fmu.set("bad_kind", kind)
        fmu.initialize()
        fmu.slave.doStep(0.0, H)
        fmu.slave.doStep(H, H)
        np.testing.assert_array_equal(fmu.get("ys"), np.full(19, 2 * H))
        fmu.expect_step_error(2 * H, H, "NaN or an infinity in output 'ys'", f"(value {index})")
        fmu.expect_step_error(3 * H, H, "Error mode", "NaN or an infinity")
        fmu.slave.reset()  # back to the start values
        fmu.set("bad_at", 0.02)
        fmu.set("bad_index", index)
        fmu.set("bad_kind", 3)  # the largest finite number is no error
        fmu.initialize()
        for k in range(4):
            fmu.slave.doStep(k * H, H)
        assert fmu.get("ys")[index] == 1.7976931348623157e308


def test_two_instances_of_one_fmu_are_independent(synthetic_fmus):
    with fmu_instance(synthetic_fmus["Echo"], instance_name="a") as a, \
            fmu_instance(synthetic_fmus["Echo"], instance_name="b") as b:
        a.initialize()
        b.initialize()
        a.set("u", 1.0)
        b.set("u", -4.0)
        for k in range(5):
            a.slave.doStep(k * H, H)
            b.slave.doStep(k * H, H)
        assert a.get("integral_u") == pytest.approx(5 * H)
        assert b.get("integral_u") == pytest.approx(-20 * H)


def test_two_builds_of_one_fmu_in_one_process_each_run_their_own_code(synthetic_fmus, tmp_path):
    """Another build of an FMU (other code, other token) loaded beside the first imports its own
    package under a name of its own, whichever build came first."""
    import shutil
    from pathlib import Path

    from fmu_build.specs import FmuSpec
    from fmu_build.package import build_fmu_from_spec

    source = tmp_path / "src" / "synthetic_fmu"
    shutil.copytree(Path(__file__).resolve().parent / "synthetic" / "synthetic_fmu", source, symlinks=False,
                    ignore=shutil.ignore_patterns("__pycache__"))
    text = (source / "fmu.py").read_text()
    old = "v.integral_u = v.integral_u + v.last_u * dt"
    assert old in text
    (source / "fmu.py").write_text(text.replace(old, "v.integral_u = v.integral_u + 2.0 * v.last_u * dt"))
    other = build_fmu_from_spec(FmuSpec("Echo", "synthetic_fmu", "fmu:ECHO", source_root=source.parent),
                                tmp_path / "fmus")
    for first, second in ((synthetic_fmus["Echo"], other), (other, synthetic_fmus["Echo"])):
        with fmu_instance(first, instance_name="a") as a, fmu_instance(second, instance_name="b") as b:
            results = []
            for fmu in (a, b):
                fmu.initialize()
                fmu.set("u", 1.0)
                fmu.slave.doStep(0.0, H)
                results.append(fmu.get("integral_u"))
        expected = [H, 2 * H] if first == synthetic_fmus["Echo"] else [2 * H, H]
        assert results == pytest.approx(expected)


# -- FMU state -------------------------------------------------------------------------------------------
#: FMU -> (steps before the save, steps after, input, value, outputs compared)
STATE_CASES = {
    "Catheter": (40, 60, "tip_force", [0.6, 0.1, 0.0],
                 ["centerline_positions", "tip_position", "bend_angle", "actuator_command"]),
    # a probe pressed into the sac wall (the default catheter points far inside the lumen, 31 of them)
    "Contact": (40, 60, "tool_positions", np.tile([0.0235, 0.0, 0.065], 31),
                ["tool_force", "tip_force", "tissue_contact_force", "patch_nodes", "passivity_energy",
                 "contact_energy"]),
    "Tissue": (3, 3, "contact_force", np.full(8064, 2e-4),
               ["surface_positions", "surface_velocities", "strain_energy", "kinetic_energy"]),
}


def _drive(fmu, name, start, steps):
    _, _, port, value, outputs = STATE_CASES[name]
    h = float(fmu.md.coSimulation.fixedInternalStepSize)
    for k in range(start, start + steps):
        fmu.slave.setFloat64(fmu.vr(port), list(np.asarray(value) * (1 + 0.01 * k)))
        fmu.slave.doStep(k * h, h)
    return {o: np.atleast_1d(fmu.get(o)).copy() for o in outputs}


@pytest.mark.parametrize("name", list(STATE_CASES))
def test_fmu_state_restores_bit_identically(name, catheter_fmu, contact_fmu, tissue_fmu, tmp_path):
    fmus = {"Catheter": catheter_fmu, "Contact": contact_fmu, "Tissue": tissue_fmu}
    before, after = STATE_CASES[name][:2]
    with fmu_instance(fmus[name]) as fmu:
        fmu.initialize()
        saved = _drive(fmu, name, 0, before)
        state = fmu.slave.getFMUState()
        first = _drive(fmu, name, before, after)
        fmu.slave.setFMUState(state)
        for port in saved:  # the outputs at the save, before any step (the models write them in place)
            np.testing.assert_array_equal(np.atleast_1d(fmu.get(port)), saved[port])
        again = _drive(fmu, name, before, after)
        serialized = fmu.slave.serializeFMUState(state)
        fmu.slave.freeFMUState(state)
    for port in first:
        np.testing.assert_array_equal(again[port], first[port])
    assert any(np.any(v != 0) for v in first.values())  # something happened after the save
    with fmu_instance(fmus[name], instance_name="fresh") as fresh:  # another instance, from the bytes
        fresh.initialize()
        restored = fresh.slave.deserializeFMUState(serialized)
        fresh.slave.setFMUState(restored)
        replay = _drive(fresh, name, before, after)
        fresh.slave.freeFMUState(restored)
    for port in first:
        np.testing.assert_array_equal(replay[port], first[port])


_PRELOAD_PROBE = r"""
import json, sys
from numba.core.registry import CPUDispatcher
from orchestration.hosts.in_process import InProcessFmu
from orchestration.hosts.description import read_fmu

description = read_fmu(sys.argv[1], {"n_tool_points": 1})  # a probe: port sizes for one point

def loaded():
    return {f"{name}.{attr}": len(d.overloads) for name, module in list(sys.modules.items())
            if name.startswith(description.model_identifier + "_") and module is not None
            for attr, d in vars(module).items() if isinstance(d, CPUDispatcher)}

host = InProcessFmu("contact", description)
host.instantiate()
at_instantiation = loaded()
host.set_values({"tool": "probe", "n_tool_points": 1})
host.enter_initialization(0.0)
host.configure(["tool_positions"], ["tool_force"])
host.exit_initialization()
for k in range(30):  # a probe from the lumen into the default wall
    host.start_step(k * 1e-3, 1e-3, {"tool_positions": [0.0227 + 1e-4 * k, 0.0, 0.065]})
    host.finish_step()
host.terminate()
print(json.dumps([at_instantiation, loaded()]))
"""


def test_cached_kernels_are_loaded_at_instantiation_not_in_a_step(contact_fmu, tmp_path):
    """numba loads a cached kernel at its first call (5-50 ms, a stall in a 1 kHz loop): the FMU
    loads them when it is instantiated. The first process fills the cache; in the second, no
    kernel is loaded after instantiation."""
    import json
    import subprocess
    import sys

    env = {**os.environ, "AAA_COSIM_NUMBA_CACHE": str(tmp_path / "numba")}
    runs = []
    for _ in range(2):
        proc = subprocess.run([sys.executable, "-c", _PRELOAD_PROBE, str(contact_fmu)], env=env,
                              capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    (first_instantiated, first_end), (instantiated, end) = runs
    assert sum(first_instantiated.values()) == 0                 # an empty cache: nothing to load
    used = {name for name, count in first_end.items() if count}
    assert len(used) >= 5                                        # the steps compiled kernels
    assert {name for name, count in instantiated.items() if count} >= used
    assert end == instantiated                                   # ... and the steps loaded none


# ---- the codes the Python runtime shares with the C layer ---------------------------------------

LAYER = Path(__file__).resolve().parent.parent / "src" / "fmi3_layer"


def _c_enums(*paths: Path) -> dict[str, int | None]:
    """Every enumerator of the enums in these C files, by name, valued as C values it (an
    enumerator without ``= value`` is the one before it plus 1, the first 0). A value this reader
    does not evaluate (other than an integer literal or ``a << b``) is None, and so are the
    enumerators that count on from it."""
    import re

    def literal(word: str) -> int:
        return int(word.rstrip("uUlL"), 0)

    enumerators = {}
    for path in paths:
        text = re.sub(r"/\*.*?\*/|//[^\n]*", " ", path.read_text(), flags=re.S)
        for body in re.findall(r"\benum\b\s*\w*\s*\{(.*?)\}", text, flags=re.S):
            value = -1
            for item in filter(None, (part.strip() for part in body.split(","))):
                name, _, given = (word.strip() for word in item.partition("="))
                if given:
                    shift = re.fullmatch(r"(\w+)\s*<<\s*(\w+)", given)
                    try:
                        value = literal(shift[1]) << literal(shift[2]) if shift else literal(given)
                    except ValueError:
                        value = None
                elif value is not None:
                    value += 1
                enumerators[name] = value
    return enumerators


def test_the_c_enum_reader_counts_as_c_does(tmp_path):
    header = tmp_path / "codes.h"
    header.write_text("/* a, b */ typedef enum { A, B, /* C = 9 */ } X;\n"
                      "enum { D = 1, E, F = 0x10u, G, // H = 3\n H = 1 << 3, I = H | D, J };\n")
    assert _c_enums(header) == {"A": 0, "B": 1, "D": 1, "E": 2, "F": 16, "G": 17, "H": 8, "I": None,
                                "J": None}


def _load_runtime():
    import importlib.util
    import sys

    name = "_test_fmi_layer_fmi3_runtime"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, LAYER / "fmi3_runtime.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


def _c_name(prefix: str, name: str) -> str:
    """The C enumerator of a Python code name: "calculatedParameter" -> C_CALCULATED_PARAMETER."""
    import re

    return prefix + re.sub(r"(?<=[a-z])(?=[A-Z])", "_", name).upper()


def test_the_runtimes_codes_are_the_c_layers():
    """fmi3_runtime.py mirrors C enums by value: fmi3Status (the standard's header), the variable
    table's type, causality and variability codes (variables.h) and the step exchange's slots
    (fmi3Functions.c). A code that drifts on either side pairs values wrongly without any error."""
    runtime = _load_runtime()
    c = _c_enums(LAYER / "include" / "fmi3FunctionTypes.h", LAYER / "variables.h", LAYER / "fmi3Functions.c")
    status = {"OK": "fmi3OK", "WARNING": "fmi3Warning", "DISCARD": "fmi3Discard", "ERROR": "fmi3Error",
              "FATAL": "fmi3Fatal"}
    pairs = {f"{name} ({c_name})": (getattr(runtime, name), c.get(c_name)) for name, c_name in status.items()}
    for table, prefix in (("TYPE_CODES", "T_"), ("CAUSALITY_CODES", "C_"), ("VARIABILITY_CODES", "V_")):
        pairs.update({f"{table}[{name!r}]": (code, c.get(_c_name(prefix, name)))
                      for name, code in getattr(runtime, table).items()})
    for name in ("IO_TIME", "IO_STEP", "IO_SUBSTEPS", "IO_STATUS", "IO_COMPLETED", "IO_MAX_SUBSTEPS",
                 "STEP_IO_SIZE"):
        pairs[name] = (getattr(runtime, name), c.get(name))
    drifted = {name: f"Python {python}, C {c_value}" for name, (python, c_value) in pairs.items()
               if python != c_value}
    assert not drifted, f"fmi3_runtime.py disagrees with the C layer: {drifted}"
    assert set(runtime.DTYPES) <= set(runtime.TYPE_CODES)
    # every slot of the step exchange has its Python name
    assert runtime.STEP_IO_SIZE == c["STEP_IO_SIZE"] == c["IO_MAX_SUBSTEPS"] + 1
