"""Fuzzing FMI call sequences on the project's FMUs, in fresh host processes: FMPy's low-level API
and the C importer (tests/fuzz_hosts.py, tests/c_host/fmu_host.c --serve), each with the model in
the host's process and in the FMU's helper process (src/fmi3_layer/remote.h).

Each case is a plain legal run of an FMU (PLAIN_RUNS: configuration, parameters, steps under
inputs, outputs; an FMU without one gets a run made from its model description) with calls
inserted that the FMU must refuse where they stand (the wrong mode, an
unknown or wrong-type value reference, more or fewer values than the references hold, a NaN or an
implausible input, a time jump, a step that is no multiple of the internal step, an output or a
fixed parameter set in Step Mode...) and legal calls that must change nothing (getters, an FMU
state saved, serialized and restored) and state handles misused (a freed state set and freed again
through a copied handle, serialized bytes with a bit flipped), which must be refused. Every case
asserts:

- the host process survives (a signal or a hang fails the case, with the calls made);
- every inserted refusal returned fmi3Error with a reason logged during that call, every plain
  call (and every inserted legal one) returned fmi3OK (a step: or fmi3Warning) without an error
  logged, no call returned fmi3Fatal or fmi3Discard;
- no Float64 read after an fmi3OK is NaN or infinite;
- the outputs at the end are bit-identical to the plain run's in the same host.

The FMUs are those of the build's table (tests/project.py), and the calls are made from the ports
each one declares (its model description): a String parameter, an input, a structural or a fixed
parameter, an output is used where the FMU has one, and the calls that need one are left out where
it has none (the synthetic FMUs of tests/synthetic check that the fuzzer runs on those too).

Cases: the hypothesis profile decides (``ci``: 25 per FMU and host; ``--hypothesis-profile=long``:
1000). Up to 10 cases share a host process (one instance each, made and freed by the case).
"""
from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fuzz_hosts import ERROR, OK, WARNING, ScriptHost, get_command, plain_run, ports, set_command
from project import FMU_NAMES

FMUS = FMU_NAMES
#: the hosts, each with the model in its own process and in the FMU's helper process
KINDS = ["fmpy", "c", "fmpy-helper", "c-helper"]


@pytest.fixture(scope="module")
def hosts(fmus, c_host, tmp_path_factory):
    """One ScriptHost per (host, FMU), shared by the module's tests; each must end normally."""
    work = tmp_path_factory.mktemp("fuzz_calls")
    made = {(kind, name): ScriptHost(kind, fmus[name], work / f"{kind}_{name}", c_host=c_host)
            for kind in KINDS for name in FMUS}
    yield made
    for host in made.values():
        host.close()
    print("fuzz_calls: cases run", {f"{k}/{n}": h.cases_run for (k, n), h in made.items()})


# ---- the calls --------------------------------------------------------------------------------------------
def _first(p, **conditions):
    """The first port (in the model description's order) with these attributes, or None."""
    for port in p.values():
        if all(getattr(port, k) == v for k, v in conditions.items()):
            return port
    return None


def _input_port(run, p):
    """The input the cases misuse: the plain run's first, else the FMU's first Float64 input (or None)."""
    return p[next(iter(run.inputs))] if run.inputs else _first(p, type="f64", causality="input")


def _largest_output(p):
    outputs = [q for q in p.values() if q.type == "f64" and q.causality == "output"]
    return max(outputs, key=lambda q: q.size) if outputs else None


def _noise_menus(run, p: dict) -> dict[str, list[tuple[str, ...]]]:
    """Per mode, items of calls to insert: each item is ("refused" | "ok", command, ...). A call
    that needs a kind of port the FMU does not declare is left out."""
    h = run.step
    scalar_output = _first(p, type="f64", causality="output", size=1)
    array_output = _largest_output(p)
    string_parameter = _first(p, type="str", causality="parameter")
    fixed_parameter = (_first(p, type="f64", causality="parameter", variability="fixed", name="internal_step")
                       or _first(p, type="f64", causality="parameter", variability="fixed"))
    structural = _first(p, type="u64", causality="structuralParameter")
    input_port = _input_port(run, p)
    limited = [q for q in p.values() if q.type == "f64" and q.causality == "input" and q.maximum is not None]
    common = [("refused", "get f64 1 9999"), ("refused", "set f64 1 9999 1.0")]
    if scalar_output:
        common.append(("refused", f"set f64 1 {scalar_output.vr} 1.0"))  # an output
    common.append(("refused", "set f64 1 0 1.0"))  # the independent variable
    if input_port:
        too_many = [repr(1e-3)] * (input_port.size + 1)
        common += [("refused", f"set f64 {len(too_many)} {input_port.vr} {' '.join(too_many)}"),  # more values
                   ("refused", f"set f64 1 {input_port.vr},{input_port.vr} 0.0")]  # fewer than the references hold
    if scalar_output:
        common.append(("refused", f"get i32 1 {scalar_output.vr}"))  # the wrong type
    if input_port:
        common.append(("refused", f"set i32 1 {input_port.vr} 1"))
    if string_parameter:
        common.append(("refused", f"get str 2 {string_parameter.vr}"))  # more strings than references
    if array_output:
        common.append(("refused", f"get f64 {array_output.size + 1} {array_output.vr}"))
    if input_port:
        common += [("refused", set_command(input_port, [float("nan")] + [0.0] * (input_port.size - 1))),
                   ("refused", set_command(input_port, [float("-inf")] * input_port.size))]
    common += [("refused", set_command(q, [q.maximum * 10 + 1] * q.size)) for q in limited]  # beyond its limit

    instantiated = [("refused", f"step 0.0 {h!r}"), ("refused", "terminate"), ("refused", "exit_init"),
                    ("refused", "exit_config")]
    if scalar_output:
        instantiated.append(("refused", get_command(scalar_output)))
    initialization = [("refused", "enter_init"), ("refused", "enter_config"), ("refused", f"step 0.0 {h!r}"),
                      ("refused", "terminate"), ("refused", "exit_config")]
    step = [("refused", "enter_init"), ("refused", "exit_init"), ("refused", "enter_config"),
            ("refused", "exit_config")]
    if fixed_parameter:
        step.append(("refused", f"set f64 1 {fixed_parameter.vr} {h!r}"))
    if structural:
        step.append(("refused", f"set u64 1 {structural.vr} 5"))
    if array_output:
        step.append(("ok", get_command(array_output)))
    if scalar_output:
        step.append(("ok", get_command(scalar_output)))
    step += [("ok", "get_state", "roundtrip_state", "set_state", "free_state"),
             ("refused", "stale_state"), ("refused", "damaged_state")]
    terminated = [("refused", f"step 0.0 {h!r}"), ("refused", "terminate"), ("refused", "enter_init")]
    if input_port:
        terminated.append(("refused", set_command(input_port, [0.0] * input_port.size)))
    if scalar_output:
        terminated.append(("ok", get_command(scalar_output)))
    never_here = {"Instantiated": instantiated, "Initialization": initialization, "Step": step,
                  "Terminated": terminated}
    return {mode: common + items for mode, items in never_here.items()}


def _time_noise(run, k: int) -> list[tuple[str, ...]]:
    """Steps refused in Step Mode at the k-th communication point (t = k h)."""
    h, t = run.step, k * run.step
    return [("refused", f"step {t + h!r} {h!r}"), ("refused", f"step {t!r} {h * 0.5!r}"),
            ("refused", f"step {t!r} {-h!r}"), ("refused", f"step {t!r} 0.0"), ("refused", f"step nan {h!r}")]


def plain_case(run, p: dict) -> list[tuple[str, str]]:
    case = [("plain", "instantiate")] + [("plain", c) for c in run.configure(p) + run.setup(p)]
    case += [("plain", "enter_init"), ("plain", "exit_init")]
    for k in range(run.steps):
        case += [("plain", c) for c in run.step_commands(p, k)]
    return case + [("plain", c) for c in run.read(p)] + [("plain", "terminate"), ("plain", "free")]


@st.composite
def noisy_cases(draw, run, p: dict):
    """The plain run with calls inserted that must be refused (or must change nothing) where they stand."""
    menus = _noise_menus(run, p)

    def noise(mode, extra=()):
        items = draw(st.lists(st.sampled_from(menus[mode] + list(extra)), max_size=2))
        return [(item[0], command) for item in items for command in item[1:]]

    case = [("plain", "instantiate")] + noise("Instantiated")
    case += [("plain", c) for c in run.configure(p)] + noise("Instantiated")
    case += [("plain", c) for c in run.setup(p)] + noise("Instantiated")
    case += [("plain", "enter_init")] + noise("Initialization") + [("plain", "exit_init")]
    for k in range(run.steps):
        case += noise("Step", _time_noise(run, k))
        case += [("plain", c) for c in run.step_commands(p, k)]
    case += noise("Step", _time_noise(run, run.steps))
    case += [("plain", c) for c in run.read(p)]
    case += [("plain", "terminate")] + noise("Terminated") + [("plain", "free")]
    return case


def check(case, answers) -> list[list[float]]:
    """Assert the rules of the module docstring on one case; the values of its plain gets, in order."""
    assert len(answers) == len(case)
    read = []
    for (expect, command), answer in zip(case, answers):
        command = command if len(command) < 160 else command[:160] + "..."
        errors = [m for s, m in answer.logs if s >= ERROR]
        assert answer.status in (OK, WARNING, ERROR), (command, answer)  # never Discard, Fatal or a crash
        if expect == "refused":
            assert answer.status == ERROR, f"{command!r} was not refused: {answer}"
            assert errors, f"{command!r} was refused without a reason"
        else:
            allowed = (OK, WARNING) if command.startswith("step") else (OK,)
            assert answer.status in allowed and not errors, f"{command!r} failed: {answer}"
        if command.startswith("get f64") and answer.status <= WARNING:
            values = [float(x) for x in answer.values]
            assert all(math.isfinite(x) for x in values), (command, answer)
            if expect == "plain":
                read.append(values)
    return read


_plain_outputs: dict = {}


def plain_outputs(host, name, run, p):
    key = (host.kind, name)
    if key not in _plain_outputs:
        case = plain_case(run, p)
        _plain_outputs[key] = check(case, host.run([c for _, c in case]))
    return _plain_outputs[key]


@pytest.mark.parametrize("name", FMUS)
def test_plain_runs_give_the_same_numbers_in_fmpy_and_the_c_host(hosts, fmus, name):
    run = plain_run(name, fmus[name])
    p = ports(fmus[name], run.structural)
    fmpy, *others = (plain_outputs(hosts[(kind, name)], name, run, p) for kind in KINDS)
    for kind, outputs in zip(KINDS[1:], others):
        assert outputs == fmpy, kind
    assert any(x != 0.0 for values in fmpy for x in values)  # the run did something


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("name", FMUS)
def test_refused_calls_inserted_in_a_legal_run_change_nothing(hosts, fmus, kind, name):
    run = plain_run(name, fmus[name])
    _refused_calls_change_nothing(hosts[(kind, name)], name, run, ports(fmus[name], run.structural))


def _refused_calls_change_nothing(host, name, run, p, examples: int | None = None) -> None:
    expected = plain_outputs(host, name, run, p)

    @_examples(examples)
    @given(noisy_cases(run, p))
    def case_runs(case):
        answers = host.run([command for _, command in case])
        read = check(case, answers)
        assert read == expected  # the plain run's outputs, bit for bit

    case_runs()


# ---- any sequence of calls -----------------------------------------------------------------------------
#: Where each kind of call is legal (FMI 3.0 Co-Simulation without Event Mode; structural
#: parameters fixed, so no Reconfiguration Mode), as tests/test_fmi_layer.py's table.
ALIVE = {"Instantiated", "Configuration", "Initialization", "Step", "Terminated", "Error"}
LEGAL = {
    "enter_init": {"Instantiated"}, "exit_init": {"Initialization"}, "enter_config": {"Instantiated"},
    "exit_config": {"Configuration"}, "step": {"Step"}, "terminate": {"Step"}, "reset": ALIVE,
    "get": ALIVE - {"Instantiated"}, "set input": {"Instantiated", "Initialization", "Step"},
    "set parameter": {"Instantiated", "Initialization"}, "set structural": {"Configuration"},
    "get_state": ALIVE - {"Configuration"}, "set_state": ALIVE - {"Configuration"},
    "free_state": ALIVE - {"Configuration"}, "roundtrip_state": ALIVE - {"Configuration"},
}
#: After fmi3OK: the mode the call leads to (None: unchanged).
LEADS_TO = {"enter_init": "Initialization", "exit_init": "Step", "enter_config": "Configuration",
            "exit_config": "Instantiated", "step": "Step", "terminate": "Terminated", "reset": "Instantiated"}


@st.composite
def call_sequences(draw, run, p: dict):
    """instantiate, up to 30 calls of any kind with plausible or broken arguments, free (calls on
    kinds of ports the FMU does not declare left out)."""
    h = run.step
    output = _largest_output(p)
    parameters = [q for q in p.values() if q.causality == "parameter" and q.type in ("f64", "i32")
                  and q.size == 1 and q.name in set(run.parameters) | {"internal_step"}]
    structural = [q for q in p.values() if q.causality == "structuralParameter"]
    input_port = _input_port(run, p)
    calls = ["enter_init", "exit_init", "enter_config", "exit_config", "terminate", "reset", "get_state", "set_state",
             "free_state", "roundtrip_state", "stale_state", "damaged_state"]
    if output:
        calls += [get_command(output), f"get f64 {output.size + 1} {output.vr}"]
    calls.append("get f64 1 9999")
    kinds = [st.sampled_from(calls),
             st.builds(lambda k, f: f"step {k * h * f!r} {h!r}", st.integers(0, 8), st.sampled_from([1.0, 1.0, 1.5]))]
    if input_port:
        kinds.append(st.builds(lambda x: set_command(input_port, x), st.sampled_from([0.0, 1e-3, float("nan"), 1e300])))
    if parameters:
        kinds.append(st.builds(lambda q, f: set_command(q, [float(q.start) * f] if q.type == "f64"
                                                        else [int(float(q.start) * f)]),
                               st.sampled_from(parameters), st.sampled_from([1.0, 0.5, -1.0])))
    if structural:
        kinds.append(st.builds(lambda q, v: set_command(q, [v]), st.sampled_from(structural),
                               st.sampled_from([0, 10**12] + [int(run.structural.get(q.name, q.start))
                                                              for q in structural])))
    return ["instantiate"] + draw(st.lists(st.one_of(kinds), max_size=30)) + ["free"]


def _kind_of(command: str, p_by_vr: dict) -> str:
    words = command.split()
    if words[0] == "set":
        port = p_by_vr.get(int(words[3].split(",")[0]))
        return {"input": "set input", "parameter": "set parameter",
                "structuralParameter": "set structural"}.get(port.causality if port else "", "set input")
    return words[0]


def check_sequence(commands, answers, p_by_vr) -> None:
    """Statuses against the legal-call table, with the modes the instance may be in followed call by call."""
    modes, saved = {"Instantiated"}, None
    for command, answer in zip(commands, answers):
        errors = [m for s, m in answer.logs if s >= ERROR]
        assert answer.status in (OK, WARNING, ERROR), answer
        if command in ("instantiate", "free"):
            assert answer.status == OK, answer
            continue
        kind = _kind_of(command, p_by_vr)
        if kind in ("stale_state", "damaged_state"):  # refused in every mode, and nothing changes
            assert answer.status == ERROR and errors, f"{command!r} in {modes} was not refused: {answer}"
            continue
        if kind in LEGAL and not (modes & LEGAL[kind]):
            assert answer.status == ERROR and errors, f"{command!r} in {modes} was not refused: {answer}"
        if answer.status == ERROR:
            assert errors, f"{command!r} returned fmi3Error without a reason"
            if kind in ("exit_init", "step", "terminate", "reset", "set_state", "exit_config", "get",
                        "roundtrip_state"):
                modes = modes | {"Error"}  # a failure of the model (or of the arguments: the mode stays)
        elif answer.status in (OK, WARNING):
            if command.startswith("get f64"):
                assert all(math.isfinite(float(x)) for x in answer.values), answer
            if kind in LEADS_TO:
                modes = {LEADS_TO[kind]}
            elif kind == "get_state":
                saved = set(modes)
            elif kind == "set_state" and saved:
                modes = set(saved)
            elif kind == "free_state":
                saved = None


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("name", FMUS)
def test_any_call_sequence_is_answered_by_the_legal_call_table(hosts, fmus, kind, name):
    """Random sequences (errors followed by more calls, resets, states restored into other modes...):
    the host survives, a call illegal in every mode the instance may be in is refused with a reason,
    no call returns fmi3Fatal or fmi3Discard, and no Float64 read after fmi3OK is NaN or infinite."""
    run = plain_run(name, fmus[name])
    _any_call_sequence_follows_the_table(hosts[(kind, name)], run, ports(fmus[name], run.structural))


def _any_call_sequence_follows_the_table(host, run, p, examples: int | None = None) -> None:
    p_by_vr = {q.vr: q for q in p.values()}
    prefix = run.configure(p) + run.setup(p)  # e.g. the coarse Tissue mesh

    @_examples(examples)
    @given(call_sequences(run, p))
    def sequence_runs(commands):
        commands = commands[:1] + prefix + commands[1:]
        answers = host.run(commands)
        assert all(a.status == OK for a in answers[1:1 + len(prefix)]), answers[:1 + len(prefix)]
        check_sequence([c for c in commands[:1]] + commands[1 + len(prefix):], answers[:1] + answers[1 + len(prefix):],
                       p_by_vr)

    sequence_runs()


# ---- the fuzzer on FMUs of other shapes ------------------------------------------------------------------
#: synthetic FMU -> calls (by their start) its menus must (True) or must not (False) hold: Signal
#: declares no input, no String and no structural parameter; Echo an input of each type, a String
#: and a structural parameter
SHAPES = {"Signal": {"get str": False, "set u64": False, "set i32": False},
          "Echo": {"get str": True, "set u64": True, "set i32": True}}


@pytest.mark.parametrize("name", list(SHAPES))
def test_the_fuzzer_makes_its_calls_from_the_ports_an_fmu_declares(synthetic_fmus, tmp_path, name):
    """An FMU without a plain run of its own (a run made from its model description) and without
    some kinds of ports: the calls use the ports it has, the rules above hold (a few cases each, in
    the FMPy host)."""
    fmu = synthetic_fmus[name]
    run = plain_run(name, fmu)
    p = ports(fmu, run.structural)
    menus = _noise_menus(run, p)
    commands = [command for items in menus.values() for item in items for command in item[1:]]
    for call, expected in SHAPES[name].items():
        assert any(c.startswith(call) for c in commands) == expected, (call, commands)
    host = ScriptHost("fmpy", fmu, tmp_path / "host")
    try:
        assert any(x != 0.0 for values in plain_outputs(host, name, run, p) for x in values)
        _refused_calls_change_nothing(host, name, run, p, examples=5)
        _any_call_sequence_follows_the_table(host, run, p, examples=5)
        assert host.cases_run > 5, host.cases_run  # the plain run, then the generated cases
    finally:
        host.close()


def _examples(examples: int | None):
    """The profile's number of cases (None), or ``examples``."""
    return (lambda test: test) if examples is None else settings(max_examples=examples)
