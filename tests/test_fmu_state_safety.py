"""FMU state is data (issue 33): the serialized bytes cannot run code, damaged or crafted bytes are
refused with a reason before anything is set, state handles are looked up before they are
followed, freed states give their memory back, and a call that would run for minutes is refused.

The serialized layout is rebuilt here from its documentation (src/fmi3_layer/state_format.py), not
from the module, so a crafted state is made the way an attacker would make one: valid magic,
version, length and SHA-256 around fields fmi3SerializeFMUState never writes.
"""
from __future__ import annotations

import hashlib
import json
import os
import pickle
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from fmu_harness import fmu_instance
from project import FMU_NAMES, entry
from test_fmi_layer import STATE_CASES, _drive

TESTS = Path(__file__).resolve().parent
PREFIX = struct.Struct("<8sIIQ32s")


def _split(data: bytes) -> tuple[dict, bytes]:
    """(document, the arrays' bytes) of a serialized state, by its documented layout."""
    magic, version, _, length, digest = PREFIX.unpack_from(data, 0)
    assert magic == b"AAAFMUST" and version == 1 and length == len(data) - PREFIX.size
    body = data[PREFIX.size:]
    assert hashlib.sha256(body).digest() == digest
    (n,) = struct.unpack_from("<Q", body, 0)
    start = (8 + n + 7) // 8 * 8
    return json.loads(body[8:8 + n]), body[start:]


def _sign(document: dict, arrays: bytes) -> bytes:
    """A state with valid framing and checksum around ``document`` (what a forger can always do)."""
    text = json.dumps(document, separators=(",", ":")).encode()
    head = struct.pack("<Q", len(text)) + text
    body = head + b"\0" * ((-len(head)) % 8) + arrays
    return PREFIX.pack(b"AAAFMUST", 1, 0, len(body), hashlib.sha256(body).digest()) + body


def _frame(body: bytes) -> bytes:
    return PREFIX.pack(b"AAAFMUST", 1, 0, len(body), hashlib.sha256(body).digest()) + body


class _Payload:
    """Unpickling this runs a shell command: what a pickle-based state loader would execute."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def _saved(fmu, name, steps=3) -> bytes:
    fmu.initialize()
    _drive(fmu, name, 0, steps)
    state = fmu.slave.getFMUState()
    data = fmu.slave.serializeFMUState(state)
    fmu.slave.freeFMUState(state)
    return data


def _driven(name: str) -> str:
    """``name``, once tests/test_fmi_layer.py's STATE_CASES says how to drive it (_drive)."""
    entry(STATE_CASES, name, "STATE_CASES of tests/test_fmi_layer.py")
    return name


@pytest.mark.parametrize("name", FMU_NAMES)
@pytest.mark.usefixtures("model_process")
def test_a_pickle_in_a_state_runs_nothing_and_is_refused(name, built_fmu, tmp_path):
    marker = tmp_path / "ran"
    evil = pickle.dumps(_Payload(marker))
    old_header = struct.pack("<8siiQddQ", b"AAAFMUS1", 8, 1, 0, 0.0, 1e-3, len(evil))  # the former format
    candidates = {
        "raw pickle": evil,
        "the former header and a pickle": old_header + evil,
        "a valid frame around a pickle": _frame(evil),
        "a valid frame, a document, then a pickle": _sign({"trees": {}, "arrays": []}, b"") + evil,
    }
    with fmu_instance(built_fmu(name)) as fmu:
        fmu.initialize()
        for what, data in candidates.items():
            fmu.expect_error(lambda: fmu.slave.deserializeFMUState(data), "fmi3DeserializeFMUState")
            assert not marker.exists(), f"{what}: the state ran a command"
        fmu.slave.doStep(0.0, float(fmu.md.coSimulation.fixedInternalStepSize))  # still usable


@pytest.mark.parametrize("node", [
    {"c": "os.system"},
    {"o": ["posix.system", 0, None]},
    {"o": ["builtins.eval", 0, None]},
    {"m": [{"o": ["fmu.CatheterFmu", 0, {"d": []}]}, "__init__"]},
    {"m": [{"l": []}, "append"]},
])
def test_a_state_naming_code_outside_the_package_is_refused(node, catheter_fmu):
    with fmu_instance(catheter_fmu) as fmu:
        document, arrays = _split(_saved(fmu, "Catheter"))
        document["trees"]["adapter_class"] = node
        fmu.expect_error(lambda: fmu.slave.deserializeFMUState(_sign(document, arrays)), "fmi3DeserializeFMUState")


@pytest.mark.parametrize("layer, words", [
    ([-1, 1, 3, 0.0, 0.001], "mode"),
    ([0xFFFFFFFF, 1, 3, 0.0, 0.001], "mode"),
    ([0x7FFFFFFF, 1, 3, 0.0, 0.001], "mode"),
    ([2, 1, 3, 0.0, 0.001], "mode"),                  # Configuration Mode: no state is saved there
    ([8, 1, 3, 0.0, float("nan")], "step"),
    ([8, 1, 3, 0.0, 0.0], "step"),
    ([8, 1, 3, 0.0, -0.001], "step"),
    ([8, 1, 10 ** 30, 0.0, 0.001], "steps"),
    ([8, 1, 3, float("inf"), 0.001], "time"),
    ([8, 1, 3, 0.0, 0.002], "internal_step"),         # not the step its parameters give
    ([8, 7, 3, 0.0, 0.001], "layer"),
])
def test_crafted_layer_fields_are_refused_and_nothing_is_set(layer, words, catheter_fmu):
    with fmu_instance(catheter_fmu) as fmu:
        document, arrays = _split(_saved(fmu, "Catheter"))
        document["layer"] = layer
        text = json.dumps(document, separators=(",", ":"))  # NaN/Infinity as a forger would write them
        data = _frame(struct.pack("<Q", len(text)) + text.encode() + b"\0" * ((-(8 + len(text))) % 8) + arrays)
        fmu.expect_error(lambda: fmu.slave.deserializeFMUState(data), "fmi3DeserializeFMUState", words)
        fmu.expect_error(fmu.slave.enterConfigurationMode, "illegal call sequence")  # still in Step Mode
        fmu.slave.doStep(3e-3, 1e-3)


@pytest.mark.parametrize("edit, words", [
    (lambda d: d.__setitem__("token", "{00000000-0000-0000-0000-000000000000}"), "another build"),
    (lambda d: d.__setitem__("model", "Tissue"), "not of Catheter"),
    (lambda d: d["variables"].pop(), "other variables"),
    (lambda d: d["trees"]["buffers"]["l"].pop(), "number of variables"),
    (lambda d: d["arrays"][0].__setitem__(0, "|O"), "dtype"),
    (lambda d: d["arrays"][-1][1].__setitem__(0, 10 ** 9), "past the end"),
    (lambda d: d["trees"]["set_counts"].__setitem__("a", 10 ** 6), "malformed"),
])
def test_a_state_of_another_build_or_size_is_refused_with_the_reason(edit, words, catheter_fmu):
    with fmu_instance(catheter_fmu) as fmu:
        document, arrays = _split(_saved(fmu, "Catheter"))
        edit(document)
        fmu.expect_error(lambda: fmu.slave.deserializeFMUState(_sign(document, arrays)), "fmi3DeserializeFMUState",
                         words)


def test_a_state_whose_sizes_contradict_its_structural_parameters_is_refused(catheter_fmu):
    with fmu_instance(catheter_fmu) as fmu:
        document, arrays = _split(_saved(fmu, "Catheter"))
        vr = [v.name for v in fmu.md.modelVariables].index("centerline_positions")
        index = document["trees"]["buffers"]["l"][vr]["a"]
        dtype, shape, offset = document["arrays"][index]
        document["arrays"][index] = [dtype, [shape[0] - 3], offset]  # three values fewer, same bytes
        fmu.expect_error(lambda: fmu.slave.deserializeFMUState(_sign(document, arrays)), "fmi3DeserializeFMUState")


@pytest.mark.parametrize("name", ["Catheter", "Tissue"])
@pytest.mark.usefixtures("model_process")
def test_single_flipped_bytes_are_refused(name, built_fmu):
    rng = np.random.default_rng(33)
    with fmu_instance(built_fmu(name)) as fmu:
        data = _saved(fmu, name)
        positions = [0, 9, 17, 30, PREFIX.size + 3] + rng.integers(PREFIX.size, len(data), 25).tolist()
        for position in positions:
            damaged = bytearray(data)
            damaged[position] ^= 1 << int(rng.integers(8))
            fmu.expect_error(lambda: fmu.slave.deserializeFMUState(bytes(damaged)), "fmi3DeserializeFMUState")
        for cut in (len(data) - 1, len(data) // 2, PREFIX.size, 7):
            fmu.expect_error(lambda: fmu.slave.deserializeFMUState(data[:cut]), "fmi3DeserializeFMUState")
        restored = fmu.slave.deserializeFMUState(data)  # the intact bytes still restore
        fmu.slave.setFMUState(restored)
        fmu.slave.freeFMUState(restored)


def _run_script(script: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(script)], capture_output=True, text=True,
                          timeout=timeout, cwd=TESTS)


@pytest.mark.parametrize("name", FMU_NAMES)
@pytest.mark.usefixtures("model_process")
def test_freed_copied_foreign_and_misplaced_handles_are_refused_not_followed(name, built_fmu):
    """A copied handle freed twice, a freed state set, a pointer that is no state, and fmusim's
    fmi3FreeFMUState(instance, state): statuses and reasons, never a crash of the importer."""
    script = f"""
        import ctypes, sys
        from fmpy.fmi3 import fmi3FMUState
        from fmu_harness import fmu_instance
        from test_fmi_layer import _drive
        from fmpy.fmi1 import FMICallException

        def status(call, *args):
            try:
                return int(call(*args))
            except FMICallException as exc:
                return exc.status

        with fmu_instance({str(built_fmu(name))!r}) as fmu:
            fmu.initialize()
            _drive(fmu, {_driven(name)!r}, 0, 2)
            s, c = fmu.slave, fmu.slave.component
            state = s.getFMUState()
            copy = fmi3FMUState(state.value)
            print("free", status(s.fmi3FreeFMUState, c, ctypes.byref(state)))
            print("free copy", status(s.fmi3FreeFMUState, c, ctypes.byref(copy)))
            print("set freed", status(s.fmi3SetFMUState, c, copy))
            newer = s.getFMUState()  # the allocator may well reuse the freed state's memory for it
            print("set freed after reuse", status(s.fmi3SetFMUState, c, copy))
            print("set newer", status(s.fmi3SetFMUState, c, newer))
            size = ctypes.c_size_t()
            print("size freed", status(s.fmi3SerializedFMUStateSize, c, copy, ctypes.byref(size)))
            junk = ctypes.create_string_buffer(64)
            print("set foreign", status(s.fmi3SetFMUState, c, fmi3FMUState(ctypes.addressof(junk))))
            reuse = fmi3FMUState(ctypes.addressof(junk))
            print("get into foreign", status(s.fmi3GetFMUState, c, ctypes.byref(reuse)))
            other = s.getFMUState()
            misplaced = ctypes.cast(other.value, ctypes.POINTER(fmi3FMUState))  # the state where its pointer is due
            print("fmusim free", status(s.fmi3FreeFMUState, c, misplaced))
            print("set after fmusim free", status(s.fmi3SetFMUState, c, other))
            again = s.getFMUState()
            s.setFMUState(again)
            _drive(fmu, {name!r}, 2, 1)
            print("messages", sum("not a live state" in m for _, m in fmu.messages))
            print("misplaced said", sum("itself, not a pointer to it" in m for _, m in fmu.messages))
        print("done")
        """
    result = _run_script(script)
    assert result.returncode == 0, result.stderr[-3000:]
    lines = dict(line.rsplit(" ", 1) for line in result.stdout.splitlines() if " " in line)
    assert lines["free"] == "0"
    assert lines["set newer"] == "0"
    for call in ("free copy", "set freed", "set freed after reuse", "size freed", "set foreign", "get into foreign",
                 "set after fmusim free"):
        assert lines[call] == "3", (call, result.stdout)
    # understood and freed, with a word why, and fmi3OK: fmusim stops at any other status (and would
    # not restore a state from its file)
    assert lines["fmusim free"] == "0" and lines["misplaced said"] == "1"
    assert int(lines["messages"]) >= 6
    assert result.stdout.strip().endswith("done")


def test_freed_tissue_states_give_their_memory_back(tissue_fmu):
    """Twenty Tissue states (tens of MB each) held at once, then freed, twice over: the process
    keeps at most a few states' worth (the allocator used to keep them: 2.2 GB after 60)."""
    result = _run_script(f"""
        import os
        from fmu_harness import fmu_instance
        from test_fmi_layer import _drive

        def rss():
            return int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

        with fmu_instance({str(tissue_fmu)!r}) as fmu:
            fmu.initialize()
            _drive(fmu, "Tissue", 0, 2)
            for k in range(3):  # warm: the first states also load what stays
                fmu.slave.freeFMUState(fmu.slave.getFMUState())
            before = rss()
            one = fmu.slave.getFMUState()
            size = rss() - before
            fmu.slave.freeFMUState(one)
            for round in range(2):
                states = [fmu.slave.getFMUState() for _ in range(20)]
                held = rss() - before
                for state in states:
                    fmu.slave.freeFMUState(state)
            print(size, held, rss() - before)
        """)
    assert result.returncode == 0, result.stderr[-3000:]
    one, held, kept = map(int, result.stdout.split())
    assert one > 20e6 and held > 10 * one  # the states are big enough for the measure to mean something
    assert kept < 4 * one, (one, held, kept)


#: FMU -> (a communication step that would run for minutes, the limit its refusal names), for every
#: FMU of the build's table (tests/project.py)
LONG_STEPS = {
    "Catheter": (1e5, "at most 100000"),
    "Contact": (1e4, "at most 100000"),
    "Tissue": (3e4, "at most 1800"),
}


@pytest.mark.parametrize("name", FMU_NAMES)
def test_a_call_that_would_run_for_minutes_is_refused_with_the_limit(name, built_fmu):
    step, words = entry(LONG_STEPS, name, "LONG_STEPS of tests/test_fmu_state_safety.py")
    with fmu_instance(built_fmu(name)) as fmu:
        fmu.initialize()
        fmu.expect_step_error(0.0, step, "split the communication step", words)
        h = float(fmu.md.coSimulation.fixedInternalStepSize)
        fmu.slave.doStep(0.0, h)  # refused, not failed: the instance goes on


@pytest.mark.parametrize("name", FMU_NAMES)
@pytest.mark.usefixtures("model_process")
def test_instantiating_again_after_the_extraction_folder_was_deleted_is_refused_not_a_crash(name, built_fmu):
    """FMPy frees the library with the instance; the same slave instantiated again after its folder
    was deleted used to jump into the unmapped library (SIGSEGV)."""
    result = _run_script(f"""
        import shutil, tempfile
        from fmpy import read_model_description, extract
        from fmpy.fmi3 import FMU3Slave
        md = read_model_description({str(built_fmu(name))!r})
        folder = extract({str(built_fmu(name))!r}, tempfile.mkdtemp())
        slave = FMU3Slave(guid=md.guid, unzipDirectory=folder, modelIdentifier=md.coSimulation.modelIdentifier,
                          instanceName="first")
        slave.instantiate()
        slave.freeInstance()
        shutil.rmtree(folder)
        try:
            slave.instantiate()
            print("instantiated")
        except Exception as exc:
            print("refused:", exc)
        """)
    assert result.returncode == 0, (result.returncode, result.stderr[-3000:])
    assert "refused:" in result.stdout


@pytest.mark.usefixtures("model_process")
def test_serialized_states_restore_in_another_process_bit_identically(catheter_fmu, tmp_path):
    """The bytes are self-contained data: a fresh interpreter restores them and continues exactly."""
    with fmu_instance(catheter_fmu) as fmu:
        data = _saved(fmu, "Catheter", 4)
        expected = _drive(fmu, "Catheter", 4, 5)
    (tmp_path / "state.bin").write_bytes(data)
    result = _run_script(f"""
        import numpy as np
        from fmu_harness import fmu_instance
        from test_fmi_layer import _drive
        with fmu_instance({str(catheter_fmu)!r}) as fmu:
            fmu.initialize()
            state = fmu.slave.deserializeFMUState(open({str(tmp_path / 'state.bin')!r}, "rb").read())
            fmu.slave.setFMUState(state)
            out = _drive(fmu, "Catheter", 4, 5)
            np.save({str(tmp_path / 'out.npy')!r}, np.concatenate([out[k].ravel() for k in sorted(out)]))
        """)
    assert result.returncode == 0, result.stderr[-3000:]
    np.testing.assert_array_equal(np.load(tmp_path / "out.npy"),
                                  np.concatenate([expected[k].ravel() for k in sorted(expected)]))
    assert len(STATE_CASES) == 3


@pytest.mark.parametrize("change", ["renamed variable", "a byte changed"])
def test_an_fmu_whose_model_description_changed_after_the_build_is_refused(change, catheter_fmu, tmp_path):
    """The importer pairs value references with the modelDescription.xml it reads: one edited after
    the build (a variable renamed) would silently pair them wrongly; the FMU refuses to instantiate."""
    from fmpy import extract, read_model_description
    from fmpy.fmi3 import FMU3Slave

    md = read_model_description(str(catheter_fmu))
    folder = Path(extract(str(catheter_fmu), str(tmp_path / "fmu")))
    description = folder / "modelDescription.xml"
    text = description.read_text()
    edited = (text.replace('name="insertion"', 'name="insertion_m"') if change == "renamed variable"
              else text.replace('description="', 'description=" ', 1))
    assert edited != text
    description.write_text(edited)
    messages = []
    slave = FMU3Slave(guid=md.guid, unzipDirectory=str(folder), modelIdentifier=md.coSimulation.modelIdentifier,
                      instanceName="edited")
    with pytest.raises(Exception, match="Failed to instantiate"):
        slave.instantiate(loggingOn=True, logMessage=lambda env, status, category, message: messages.append(
            message.decode()))
    slave.freeLibrary()
    assert any("not the modelDescription.xml this FMU was built with" in m for m in messages), messages


def test_an_fmu_extracted_without_its_model_description_still_runs(catheter_fmu):
    """FMPy's simulate_fmu extracts only the binaries and resources (it reads the XML from the
    archive): the FMU has nothing to compare and runs."""
    from fmpy import simulate_fmu

    result = simulate_fmu(str(catheter_fmu), stop_time=0.01, output=["bend_angle"])
    assert len(result) == 11


def _find_key(node, key):
    """The [key, value] pair of ``key`` anywhere in a state's tree (dict entries are [key, value])."""
    if isinstance(node, dict):
        for value in node.values():
            found = _find_key(value, key)
            if found:
                return found
    elif isinstance(node, list):
        if len(node) == 2 and node[0] == key:
            return node
        for value in node:
            found = _find_key(value, key)
            if found:
                return found
    return None


@pytest.mark.parametrize("replacement, words", [
    ("text", "passive_bend is a str"),
    ("set_counts", "passive_bend is a uint64 array"),
    ({"l": [1.0, 2.0]}, "passive_bend is a list"),
])
@pytest.mark.parametrize("initialized", [True, False])
def test_a_model_state_that_is_not_the_models_is_refused_and_nothing_is_set(replacement, words, initialized,
                                                                             catheter_fmu):
    """Valid bytes whose model part has another kind of value than the model its parameters build
    (a forger's state): refused by fmi3SetFMUState with where it differs; the instance goes on."""
    with fmu_instance(catheter_fmu) as fmu:
        data = _saved(fmu, "Catheter")
        expected = _drive(fmu, "Catheter", 3, 2)
    document, arrays = _split(data)
    pair = _find_key(document["trees"]["adapter_state"], "passive_bend")
    pair[1] = document["trees"]["set_counts"] if replacement == "set_counts" else replacement
    with fmu_instance(catheter_fmu, instance_name="other") as fmu:
        if initialized:
            fmu.initialize()
        state = fmu.slave.deserializeFMUState(_sign(document, arrays))
        fmu.expect_error(lambda: fmu.slave.setFMUState(state), "fmi3SetFMUState", "does not match", words)
        if initialized:  # refused before anything was set: still in Step Mode, where it was
            fmu.slave.doStep(0.0, 1e-3)
        else:  # still Instantiated
            fmu.slave.enterConfigurationMode()
            fmu.slave.exitConfigurationMode()
        good = fmu.slave.deserializeFMUState(data)  # the genuine state still restores, built or not
        fmu.slave.setFMUState(good)
        again = _drive(fmu, "Catheter", 3, 2)
    for port in expected:
        np.testing.assert_array_equal(again[port], expected[port])
