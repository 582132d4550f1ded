"""Fuzzing serialized FMU states (issue 33): bytes damaged anywhere, and states whose document a
forger edited and signed again (any value of any field replaced by any JSON value, tags and all).

Every case asserts that the importer survives and is answered:
- damaged bytes are refused by fmi3DeserializeFMUState (the SHA-256 or the framing), always;
- a re-signed edit is refused by fmi3DeserializeFMUState or fmi3SetFMUState with fmi3Error and a
  reason, or restores a state from which steps end in fmi3OK, fmi3Warning or fmi3Error (never a
  crash, a hang or another exception), and the instance restores the genuine state afterwards.

Cases run in this process on every FMU of the build's table (tests/project.py) but those in
LEFT_OUT, which says why (a crash fails the run, which is the point).
The hypothesis profile decides how many (``ci``: 25 per test; ``--hypothesis-profile=long``: 1000).
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from fmpy.fmi1 import FMICallException
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from fmu_harness import FmuInstance
from project import FMU_NAMES, entry
from test_fmi_layer import STATE_CASES, _drive
from test_fmu_state_safety import PREFIX, _sign, _split

#: FMUs of the table not fuzzed here, and why
LEFT_OUT = {"Tissue": "its state is tens of MB (the default wall): a case would take seconds, not milliseconds; "
                      "tests/test_fmu_state_safety.py damages its bytes"}
NAMES = sorted(name for name in FMU_NAMES if name not in LEFT_OUT)  # sorted: the cases do not follow the table's order


class _Saved(dict):
    def __repr__(self):  # hypothesis prints the fixture with a failing case: not the megabytes
        return "<saved states>"


@pytest.fixture(scope="module")
def saved(built_fmu):
    """Per FMU: an initialized instance, the genuine serialized state and the outputs after it."""
    made = _Saved()
    for name in NAMES:
        entry(STATE_CASES, name, "STATE_CASES of tests/test_fmi_layer.py (how _drive drives it)")
        fmu = FmuInstance(built_fmu(name), instance_name=f"fuzz_{name}")
        fmu.initialize()
        _drive(fmu, name, 0, 3)
        state = fmu.slave.getFMUState()
        data = fmu.slave.serializeFMUState(state)
        expected = _drive(fmu, name, 3, 2)
        fmu.slave.setFMUState(state)
        fmu.slave.freeFMUState(state)
        made[name] = (fmu, data, expected)
    yield made
    for fmu, _, _ in made.values():
        fmu.close()


def _restores_genuinely(fmu, name, data, expected):
    fmu.messages.clear()
    state = fmu.slave.deserializeFMUState(data)
    fmu.slave.setFMUState(state)
    fmu.slave.freeFMUState(state)
    again = _drive(fmu, name, 3, 2)
    for port in expected:
        np.testing.assert_array_equal(again[port], expected[port])


@settings(suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(name=st.sampled_from(NAMES), data=st.data())
def test_damaged_bytes_are_always_refused(saved, name, data):
    fmu, genuine, expected = saved[name]
    damaged = bytearray(genuine)
    kind = data.draw(st.sampled_from(["flip", "truncate", "append", "splice"]))
    if kind == "flip":
        for _ in range(data.draw(st.integers(1, 4))):
            damaged[data.draw(st.integers(0, len(damaged) - 1))] ^= data.draw(st.integers(1, 255))
    elif kind == "truncate":
        del damaged[data.draw(st.integers(0, len(damaged) - 1)):]
    elif kind == "append":
        damaged += data.draw(st.binary(min_size=1, max_size=64))
    else:
        at = data.draw(st.integers(PREFIX.size, len(damaged) - 1))
        damaged[at:at] = data.draw(st.binary(min_size=1, max_size=16))
    assume(bytes(damaged) != genuine)  # two flips of one bit undo each other
    fmu.messages.clear()
    with pytest.raises(FMICallException) as refused:
        fmu.slave.deserializeFMUState(bytes(damaged))
    assert refused.value.status == 3 and any("fmi3DeserializeFMUState" in m for m in fmu.errors())
    _restores_genuinely(fmu, name, genuine, expected)


_json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-2 ** 70, 2 ** 70) | st.sampled_from([0, 1, -1, 2 ** 63, 10 ** 9])
    | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=12)
    | st.sampled_from(["model.CatheterModel", "fmu.ContactFmu", "os.system", "builtins.eval", "<f8", "|O"]),
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.sampled_from(["a", "o", "r", "c", "m", "n", "f", "l", "t", "d", "x"]), children,
                      max_size=2),
    max_leaves=12)


def _paths(node, path=()):
    """Every place in a JSON document a value can be replaced at."""
    yield path
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _paths(value, path + (key,))
    elif isinstance(node, list):
        for index, value in enumerate(node):
            yield from _paths(value, path + (index,))


@settings(suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(name=st.sampled_from(NAMES), data=st.data())
def test_edited_and_resigned_states_are_refused_or_restore_a_state_that_steps(saved, name, data):
    fmu, genuine, expected = saved[name]
    document, arrays = _split(genuine)
    paths = [p for p in _paths(document) if p]
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(paths))
        parent = document
        try:
            for key in path[:-1]:
                parent = parent[key]
            parent[path[-1]] = data.draw(_json_values)
        except (KeyError, IndexError, TypeError):  # an earlier edit removed the place
            pass
    text = json.dumps(document, separators=(",", ":"))
    forged = _sign(json.loads(text), arrays) if "NaN" not in text and "Infinity" not in text else None
    if forged is None:  # what json.dumps wrote, NaN and all, framed by hand
        head = len(text).to_bytes(8, "little") + text.encode()
        body = head + b"\0" * ((-len(head)) % 8) + arrays
        import hashlib
        forged = PREFIX.pack(b"AAAFMUST", 1, 0, len(body), hashlib.sha256(body).digest()) + body
    fmu.messages.clear()
    try:
        state = fmu.slave.deserializeFMUState(forged)
    except FMICallException as exc:
        assert exc.status == 3 and fmu.errors(), fmu.messages
    else:
        try:
            fmu.slave.setFMUState(state)
        except FMICallException as exc:
            assert exc.status == 3 and fmu.errors(), fmu.messages
        else:
            h = float(fmu.md.coSimulation.fixedInternalStepSize)
            time = fmu.get("time") if "time" in fmu.vars else None
            for k in range(3):
                try:
                    fmu.slave.doStep(float(time) + k * h if time is not None else k * h, h)
                except FMICallException as exc:
                    assert exc.status == 3, fmu.messages
                    break
        finally:
            fmu.slave.freeFMUState(state)
    _restores_genuinely(fmu, name, genuine, expected)
