"""Numbers the Python side and the C side must agree on, checked against the C sources.

The compiled loop reads its operations, stop reasons and casts from compiled_loop.c itself
(``c_constants``); the FMI status numbers of the binding come from the FMI 3.0 headers.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from orchestration import errors
from orchestration.run import compiled_loop

ROOT = Path(__file__).resolve().parent.parent
FMI_HEADER = ROOT / "src" / "fmi3_layer" / "include" / "fmi3FunctionTypes.h"


def test_c_constants_counts_enums_as_c_does():
    source = """
    #define LIMIT 42
    #define NAME_ONLY
    enum { A = 0, B, C = 7, D };
    typedef enum {
        x1,
        x2 = 0x10,
        x3
    } named;
    """
    assert compiled_loop.c_constants(source) == {"LIMIT": 42, "A": 0, "B": 1, "C": 7, "D": 8, "x1": 0, "x2": 16,
                                                 "x3": 17}


def test_the_step_cost_bins_are_those_of_the_compiled_loop():
    """The compiled loop bins the steps it times in C; the summary reads the bins in Python."""
    from orchestration.run import step_costs

    constants = compiled_loop.c_constants(compiled_loop.SOURCE.read_text())
    assert constants["COST_LINEAR_BITS"] == step_costs.LINEAR_BITS
    assert constants["COST_SUB_BITS"] == step_costs.SUB_BITS
    # every bin's middle falls back in its bin, and the bins are contiguous and increasing
    for index in range(0, step_costs.BINS - 1, 7):
        assert step_costs.cost_bin(int(step_costs._bin_middle(index))) == index


def test_the_compiled_loops_numbers_are_those_of_its_c_source():
    constants = compiled_loop.c_constants(compiled_loop.SOURCE.read_text())
    for name in ("OP_NOP", "OP_BEGIN", "OP_SET", "OP_STEP", "OP_GET", "OP_END", "OP_COPY", "OP_WINDOW", "OP_PACE",
                 "OP_LATE", "OP_MEAN", "DONE", "CALL_FAILED", "ERROR_LOGGED", "STEP_FLAGS", "BAD_OP", "NOT_EXACT"):
        assert getattr(compiled_loop, name) == constants[name], name
    casts = {name: value for name, value in constants.items() if name.startswith("CAST_")}
    assert sorted(compiled_loop._CASTS.values()) == sorted(casts.values())  # every cast has its dtype
    assert compiled_loop._CASTS[np.dtype(np.float64)] == casts["CAST_NONE"]
    assert compiled_loop._CASTS[np.dtype(np.uint64)] == casts["CAST_UINT64"]
    # the statuses compiled_loop.c compares fmi3DoStep's result with
    assert constants["FMI_WARNING"] == errors.FMI_WARNING and constants["FMI_DISCARD"] == errors.FMI_DISCARD


def test_the_bindings_status_numbers_are_those_of_the_fmi_header():
    header = FMI_HEADER.read_text()
    body = header[header.index("typedef enum", header.index("fmi3Status") - 200):]
    constants = compiled_loop.c_constants(body[:body.index("fmi3Status;") + len("fmi3Status;")])
    assert {name: constants[name] for name in errors.STATUS_NAMES} == dict(zip(errors.STATUS_NAMES, range(5)))
    assert [errors.FMI_OK, errors.FMI_WARNING, errors.FMI_DISCARD, errors.FMI_ERROR, errors.FMI_FATAL] == \
        [constants[name] for name in errors.STATUS_NAMES]
