"""The FMU's helper process (src/fmi3_layer/remote.h) when things go wrong around it.

A helper that dies (killed, out of memory) must not hang or kill its importer: the next call
returns fmi3Fatal with a log line saying what happened. An importer that dies must not leave its
helpers running. Each case runs in a fresh FMPy process with the model forced into the helper.
"""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

FIND_HELPERS = """
def helpers():
    import os
    found = []
    for task in os.listdir(f"/proc/{os.getpid()}/task"):
        for child in open(f"/proc/{os.getpid()}/task/{task}/children").read().split():
            if b"aaa_cosim_helper" in open(f"/proc/{child}/cmdline", "rb").read():
                found.append(int(child))
    return found
"""


def _run(script: str, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {**os.environ, "AAA_COSIM_MODEL_PROCESS": "helper"}
    return subprocess.run([sys.executable, "-c", textwrap.dedent(script)], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=str(Path(__file__).parent))


def test_a_helper_killed_during_a_run_makes_the_next_call_fatal_not_a_hang(catheter_fmu):
    result = _run(FIND_HELPERS + f"""
import os, signal
from fmu_harness import fmu_instance
with fmu_instance({str(catheter_fmu)!r}) as fmu:
    fmu.initialize()
    fmu.slave.doStep(0.0, 0.001)
    (helper,) = helpers()
    os.kill(helper, signal.SIGKILL)
    try:
        fmu.slave.doStep(0.001, 0.001)
        print("step", "ok")
    except Exception as exc:
        print("step", type(exc).__name__, exc)
    print("said", any("helper process" in m and "ended" in m for _, m in fmu.messages))
print("importer alive")
""")
    assert result.returncode == 0, result.stderr[-3000:]
    lines = dict(line.split(" ", 1) for line in result.stdout.splitlines() if " " in line)
    assert "status 4" in lines["step"] or "Fatal" in lines["step"], lines["step"]  # fmi3Fatal
    assert lines["said"] == "True"
    assert "importer alive" in result.stdout


def test_a_helper_ends_with_its_importer(catheter_fmu):
    result = _run(FIND_HELPERS + f"""
import os
from fmu_harness import fmu_instance
context = fmu_instance({str(catheter_fmu)!r})  # kept: a dropped context would free the instance
fmu = context.__enter__()
fmu.initialize()
print(*helpers(), flush=True)
os._exit(0)  # the importer dies without freeing anything
""")
    assert result.returncode == 0, result.stderr[-3000:]
    (helper,) = map(int, result.stdout.split())
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and Path(f"/proc/{helper}").exists():
        state = Path(f"/proc/{helper}/stat").read_text().split()[2] if Path(f"/proc/{helper}/stat").exists() else "X"
        if state == "Z":  # ended, waiting to be reaped by init
            break
        time.sleep(0.1)
    else:
        if Path(f"/proc/{helper}").exists():
            pytest.fail(f"the helper {helper} still runs 10 s after its importer died")
