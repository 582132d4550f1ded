"""FMU hosts of the orchestrator: in-process (raw ctypes) and worker process (pipe + shared memory).

Known answers: the synthetic FMUs' outputs are exact functions of time and inputs; the worker
must reproduce the in-process results bit for bit; errors and crashes must name the component,
the call and the simulated time; nothing may leak (shared memory, processes).
"""
from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import subprocess
import sys
import textwrap
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from orchestration.errors import FmuCallError, WorkerCrash
from orchestration.hosts.in_process import ComponentHost, InProcessFmu, PortConfigurationError
from orchestration.hosts.description import read_fmu
from orchestration.hosts.worker import WorkerFmu

HOSTS = {"in_process": InProcessFmu, "worker": WorkerFmu}
H = 0.01  # the synthetic FMUs' communication step


def shm_exists(name: str) -> bool:
    return (Path("/dev/shm") / name.lstrip("/")).exists()


@contextmanager
def hosted(kind: str, name: str, fmu: Path, structural: dict | None = None):
    host = HOSTS[kind](name, read_fmu(fmu, structural))
    try:
        yield host
    finally:
        host.terminate()


def start(host, inputs=(), observed=(), values=None, t0=0.0):
    host.instantiate()
    if values:
        host.set_values(values)
    host.enter_initialization(t0)
    host.configure(list(inputs), list(observed))
    host.exit_initialization()


@pytest.fixture(params=list(HOSTS))
def kind(request) -> str:
    return request.param


# -- the real Contact FMU: worker and in-process agree bit for bit ---------------------------------
def scripted_tool(k: int, n_points: int = 31) -> np.ndarray:
    """A straight catheter piece in the sac (z 60..70 mm), pushed off-axis to x = 26 mm and back.

    The default AAA lumen is about 25 mm in radius there and the tool radius is 1 mm, so the
    tool touches the wall for roughly the middle half of the 200 steps.
    """
    x = 0.016 + 0.010 * np.sin(np.pi * k / 200)
    z = np.linspace(0.060, 0.070, n_points)
    return np.column_stack([np.full(n_points, x), np.zeros(n_points), z]).ravel()


CONTACT_OUTPUTS = ["tool_force", "tip_force", "tissue_contact_force", "penetration_depth", "contact_energy",
                   "passivity_energy", "contact_count"]


def run_contact(kind: str, fmu: Path, steps: int = 200) -> list[dict[str, np.ndarray]]:
    with hosted(kind, "Contact", fmu) as host:
        host.instantiate()
        host.enter_initialization(0.0)
        host.configure(["tool_positions"], CONTACT_OUTPUTS)
        host.set_inputs({"tool_positions": scripted_tool(0)})
        host.exit_initialization()
        results = []
        for k in range(steps):
            host.start_step(k * 0.001, 0.001, {"tool_positions": scripted_tool(k)})
            results.append({k: v.copy() for k, v in host.finish_step().items()})  # valid until the next step
    return results


def test_contact_worker_matches_in_process_bitwise(contact_fmu):
    local = run_contact("in_process", contact_fmu)
    remote = run_contact("worker", contact_fmu)
    force = np.array([r["tool_force"] for r in local])
    touching = np.array([r["contact_count"][0] > 0 for r in local])
    # contact really happens, and only for part of the run
    assert 20 < touching.sum() < 180
    assert np.all(np.linalg.norm(force[~touching], axis=1) == 0.0)
    # while the tool moves out (first half) the wall pushes it back towards the axis (-x); while
    # it retracts, penalty damping may pull slightly. The tissue gets the reaction of the law's
    # force at the sampled depths; the device the force held over the predicted depths (the tool
    # moves up to 0.16 mm a step: 0.2-5.5 times the law's), along the same normals: all of it up
    # to the device's 7.9 N, then 7.9 N (the 2 mm deep piece asks for more)
    pushing = touching & (np.arange(len(local)) <= 100)
    assert pushing.sum() > 10 and np.all(force[pushing, 0] < 0.0)
    limited = 0
    for r in (r for r, t in zip(local, touching) if t):
        reaction = r["tissue_contact_force"].reshape(-1, 3).sum(axis=0)
        held = np.linalg.norm(r["tool_force"])
        if held > 0.0 and np.linalg.norm(reaction) > 0.0:
            # along the reaction, but for the direction's change within a step (the rate limit
            # blends in the previous sample's force) and the contacts' normals along the tool (within
            # 1e-5 of each other), which the held and the law's forces weight differently
            np.testing.assert_allclose(r["tool_force"] / held, -reaction / np.linalg.norm(reaction), atol=1e-5)
        if held == pytest.approx(7.9, rel=1e-12):
            limited += 1
        assert held <= 7.9 * (1 + 1e-12)
    assert limited > 0
    for a, b in zip(local, remote):
        assert a.keys() == b.keys() == set(CONTACT_OUTPUTS)
        for name in a:
            assert a[name].dtype == b[name].dtype == np.float64
            assert a[name].tobytes() == b[name].tobytes(), name


# -- synthetic FMUs: exact known answers -----------------------------------------------------------
def test_signal_is_the_polynomial_bit_for_bit(kind, synthetic_fmus):
    a, b, c = 0.3, -1.7, 2.9
    with hosted(kind, "sig", synthetic_fmus["Signal"]) as host:
        start(host, observed=["y", "y3", "count", "odd"], values={"coefficients": np.array([a, b, c])})
        out = host.get_outputs()
        assert out["y"].tolist() == [a] and out["count"].tolist() == [0.0] and out["odd"].tolist() == [0.0]
        for k in range(25):
            t = k * H
            host.start_step(t, H, {})
            out = host.finish_step()
            now = t + H
            y = a + b * now + c * now * now
            assert out["y"].tobytes() == np.array([y]).tobytes()
            assert out["y3"].tolist() == [y, now, 1.0]
            assert out["count"].tolist() == [k + 1.0]
            assert out["odd"].tolist() == [float((k + 1) % 2)]


def test_every_value_type_round_trips(kind, synthetic_fmus):
    observed = ["last_u", "last_v", "last_k", "last_b", "last_w", "last_t", "integral_u", "label_length",
                "flag_echo"]
    script = [  # u, v, k, b: extreme but exact values of each type
        (0.1, [1 / 3, -0.0, 5e-324], 2**31 - 1, True),
        (-1e300, [np.pi, 1e-300, -2.5], -(2**31), False),
        (np.nextafter(1.0, 2.0), [7.0, 8.0, 9.0], 0, True),
    ]
    with hosted(kind, "echo", synthetic_fmus["Echo"], {"n_w": 4}) as host:
        assert isinstance(host, ComponentHost)
        start(host, inputs=["u", "v", "k", "b", "w"], observed=observed,
              values={"label": "hello world", "flag": True, "n_w": 4, "u": 42.0})
        before = host.get_outputs()
        # before the first step last_* are the start values (u = 42 is only the input's value now)
        assert before["last_u"].tolist() == [0.0] and before["last_w"].tolist() == [0.0] * 4
        assert before["label_length"].tolist() == [11.0] and before["flag_echo"].tolist() == [1.0]
        integral = 0.0
        for k, (u, v, i, flag) in enumerate(script):
            w = np.arange(4.0) * (k + 1) + 0.25
            t = k * H
            host.start_step(t, H, {"u": np.array([u]), "v": np.array(v), "k": np.array([float(i)]),
                                   "b": np.array([float(flag)]), "w": w})
            out = host.finish_step()
            integral += u * H
            assert out["last_u"].tobytes() == np.array([u]).tobytes()
            assert out["last_v"].tobytes() == np.array(v).tobytes()  # -0.0 and the subnormal survive
            assert out["last_k"].tolist() == [float(i)] and out["last_b"].tolist() == [float(flag)]
            assert out["last_w"].tolist() == w.tolist() and out["last_t"].tolist() == [t]
            assert out["integral_u"].tolist() == [integral]
        # inputs not given keep their previous values; given as a subset they still land
        host.start_step(len(script) * H, H, {"k": np.array([-5.0])})
        out = host.finish_step()
        assert out["last_k"].tolist() == [-5.0] and out["last_u"].tolist() == [script[-1][0]]
        # values that the FMU's type cannot hold exactly are refused before reaching it
        with pytest.raises(ValueError, match="whole numbers"):
            host.set_inputs({"k": np.array([2.5])})
        with pytest.raises(ValueError, match=r"0 or 1"):
            host.set_inputs({"b": np.array([0.5])})
        with pytest.raises(ValueError, match="expects 3 value"):
            host.set_inputs({"v": np.zeros(2)})
        with pytest.raises(ValueError, match="expects 3 value"):  # one value is not spread over three
            host.set_inputs({"v": np.ones(1)})
        with pytest.raises(ValueError, match="not among the configured inputs"):
            host.set_inputs({"last_u": np.zeros(1)})


def test_set_values_refuses_wrong_types_with_the_port_named(synthetic_fmus):
    with hosted("in_process", "echo", synthetic_fmus["Echo"]) as host:
        host.instantiate()
        for values, words in [({"n_w": 2.5}, "whole number"), ({"flag": "yes"}, "Boolean"),
                              ({"label": 3}, "String"), ({"nope": 1.0}, "no variable"),
                              ({"n_w": -1}, "out of its range")]:
            with pytest.raises(PortConfigurationError, match=words):
                host.set_values(values)
    with pytest.raises(PortConfigurationError, match="not an input"):
        with hosted("in_process", "echo", synthetic_fmus["Echo"]) as host:
            host.instantiate()
            host.configure(["last_u"], [])


# -- errors and crashes ----------------------------------------------------------------------------
def test_fmu_error_names_call_time_and_logged_reason(kind, synthetic_fmus, caplog):
    with hosted(kind, "faulty", synthetic_fmus["Faulty"]) as host:
        start(host, observed=["y"], values={"error_at": 0.05})
        with pytest.raises(FmuCallError) as info:
            for k in range(10):
                host.start_step(k * H, H, {})
                assert host.finish_step()["y"].tolist() == [k * H + H]
        error = info.value
        assert not isinstance(error, WorkerCrash)
        assert (error.component, error.call, error.time, error.status) == ("faulty", "fmi3DoStep", 5 * H, 3)
        assert "requested error at t = 0.05" in error.reason
        assert str(error).startswith("faulty: fmi3DoStep at t = 0.050000 s failed (fmi3Error): ")
        assert any(status == 3 and "requested error" in text for status, text in host.messages)
        assert any(r.name == "orchestration.fmu.faulty" and "requested error" in r.getMessage()
                   for r in caplog.records)
        # the failed instance refuses further steps, and says why
        with pytest.raises(FmuCallError, match="fmi3DoStep") as info:
            host.start_step(6 * H, H, {})
            host.finish_step()
        assert "Error mode" in info.value.reason and "requested error" in info.value.reason


def test_worker_crash_is_reported_and_a_new_worker_starts(synthetic_fmus):
    children_before = set(multiprocessing.active_children())
    host = WorkerFmu("faulty", read_fmu(synthetic_fmus["Faulty"]))
    try:
        start(host, observed=["y"], values={"crash_at": 0.03})
        shm_name = host._shm.name
        with pytest.raises(WorkerCrash) as info:
            for k in range(10):
                host.start_step(k * H, H, {})
                host.finish_step()
        crash = info.value
        assert (crash.component, crash.call, crash.time) == ("faulty", "fmi3DoStep", 3 * H)
        assert "SIGABRT" in crash.reason and "faulty: fmi3DoStep at t = 0.030000 s failed" in str(crash)
        with pytest.raises(WorkerCrash, match="get_outputs.*SIGABRT"):
            host.get_outputs()
    finally:
        host.terminate()
    host.terminate()
    assert not shm_exists(shm_name)
    # the master lives on: a new worker in the same process works
    with hosted("worker", "sig", synthetic_fmus["Signal"]) as signal_host:
        start(signal_host, observed=["count"])
        signal_host.start_step(0.0, H, {})
        assert signal_host.finish_step()["count"].tolist() == [1.0]
    assert set(multiprocessing.active_children()) == children_before


def test_killed_idle_worker_is_reported_by_the_next_call(synthetic_fmus):
    with hosted("worker", "sig", synthetic_fmus["Signal"]) as host:
        start(host, observed=["y"])
        os.kill(host._process.pid, signal.SIGKILL)
        with pytest.raises(WorkerCrash, match=r"sig: fmi3DoStep at t = 0\.000000 s failed: .*SIGKILL"):
            host.start_step(0.0, H, {})
            host.finish_step()


# -- concurrency handle, termination and leaks -----------------------------------------------------
def test_workers_step_concurrently_and_say_when_done(synthetic_fmus):
    with hosted("worker", "a", synthetic_fmus["Signal"]) as a, hosted("worker", "b", synthetic_fmus["Signal"]) as b:
        for host in (a, b):
            start(host, observed=["count"])
            assert host.step_done()  # nothing in flight
        for k in range(3):
            for host in (a, b):
                host.start_step(k * H, H, {})
            pending = [a, b]
            deadline = time.monotonic() + 30
            while pending:  # both steps in flight at once; each collected once it says it is done
                assert time.monotonic() < deadline, "a worker's step did not end in 30 s"
                for host in [h for h in pending if h.step_done()]:
                    pending.remove(host)
                    assert host.finish_step()["count"].tolist() == [k + 1.0]
    with hosted("in_process", "c", synthetic_fmus["Signal"]) as c:
        assert c.step_done()


def test_terminate_is_idempotent_and_leaves_nothing(kind, synthetic_fmus):
    host = HOSTS[kind]("echo", read_fmu(synthetic_fmus["Echo"]))
    start(host, inputs=["u"], observed=["last_u"])
    host.start_step(0.0, H, {"u": np.array([1.0])})
    host.finish_step()
    host.start_step(H, H, {"u": np.array([2.0])})  # a step still in flight at terminate
    if kind == "worker":
        shm_name = host._shm.name
        assert shm_exists(shm_name)  # the check below can see a leak
        pid = host._process.pid
    else:
        unzip_dir = Path(host._unzip_dir)
        assert unzip_dir.is_dir()
    host.terminate()
    host.terminate()
    if kind == "worker":
        assert not shm_exists(shm_name)
        with pytest.raises(ProcessLookupError):  # reaped, not a zombie
            os.kill(pid, 0)
        assert not [p for p in multiprocessing.active_children() if p.name == "fmu-worker-echo"]
    else:
        assert not unzip_dir.exists()
    with pytest.raises(RuntimeError, match="after terminate"):
        host.get_outputs()


def test_a_run_that_fails_in_initialization_frees_without_an_illegal_terminate(kind, synthetic_fmus, caplog):
    """fmi3Terminate is not allowed in Initialization Mode (FMI 3.0 state machine): a host ended
    there (a run that failed while initializing) frees its instance without calling it."""
    host = HOSTS[kind]("echo", read_fmu(synthetic_fmus["Echo"]))
    host.instantiate()
    host.enter_initialization(0.0)
    with caplog.at_level(logging.WARNING):
        host.terminate()
    assert not [r for r in caplog.records if "Terminate" in r.getMessage() or "illegal" in r.getMessage()]


def test_building_an_fmu_does_not_break_instances_loaded_in_this_process(contact_fmu, tmp_path):
    """Regression (fresh-clone CI): a build inside a process that had loaded Contact.fmu replaced
    the package module the reused entry module refers to, and the next Contact instance failed
    with "No module named 'Contact_haptic_fmu'". Builds now run in a fresh interpreter."""
    from fmu_build.package import build_fmu
    from orchestration.hosts.in_process import InProcessFmu
    from orchestration.hosts.description import read_fmu

    def one_instance(path):
        host = InProcessFmu("contact", read_fmu(path))
        try:
            host.instantiate()
            host.enter_initialization(0.0)
            host.configure([], ["tool_force"])
            host.exit_initialization()
            host.start_step(0.0, 0.001, {})
            return host.finish_step()["tool_force"]
        finally:
            host.terminate()

    np.testing.assert_array_equal(one_instance(contact_fmu), np.zeros(3))
    rebuilt = build_fmu("Contact", tmp_path)
    np.testing.assert_array_equal(one_instance(rebuilt), np.zeros(3))
    np.testing.assert_array_equal(one_instance(contact_fmu), np.zeros(3))


def test_a_worker_that_dies_at_start_up_is_reported_not_waited_for(tissue_fmu, tmp_path):
    """A worker process starts by importing the main script. A script that starts a run when
    imported (no ``if __name__ == "__main__":``) makes the worker die at start-up; the master
    must report that with the fix, not hang. The Tissue FMU's description (its ports' start
    values) is larger than a pipe's buffer: handing it to the starting process blocked forever."""
    script = tmp_path / "unguarded.py"
    script.write_text(textwrap.dedent(f"""
        from orchestration.hosts.description import read_fmu
        from orchestration.hosts.worker import WorkerFmu

        host = WorkerFmu("tissue", read_fmu({str(tissue_fmu)!r}))
        try:
            host.instantiate()
        except Exception as exc:
            if __name__ != "__main__":  # in the worker: dies of it, as any unguarded script does
                raise
            print("REPORTED:", exc)
        finally:
            host.terminate()
        print("DONE")
    """))
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    out = result.stdout
    assert result.returncode == 0, result.stderr[-2000:]
    assert out.count("DONE") == 1, out  # the worker never ran the script to its end
    assert "REPORTED: tissue: start worker" in out and "died" in out, out
    assert 'if __name__ == "__main__":' in out, out


def test_a_tissue_worker_factorises_on_one_thread(tissue_fmu, contact_fmu, monkeypatch):
    """A worker caps native thread pools before it loads its FMU (orchestration.hosts.native_threads):
    the tissue's CHOLMOD (the cholmod extra) would otherwise start 3 OpenMP threads and a BLAS
    pool in the worker, whose CPU a 2-core machine shares with the haptic loop. So a tissue worker
    that has factorised its wall and stepped runs as many threads as a contact worker. The master's
    environment has no limits here: the worker sets them itself."""
    from tissue_fmu.factorization import backend_available

    if not backend_available("scikit-sparse"):
        pytest.skip("scikit-sparse (the system's CHOLMOD) not installed")
    from orchestration.hosts.native_threads import NATIVE_THREAD_LIMITS

    for name in NATIVE_THREAD_LIMITS:
        monkeypatch.delenv(name, raising=False)
    threads = {}
    for name, fmu, h in (("tissue", tissue_fmu, 1 / 30), ("contact", contact_fmu, 0.001)):
        with hosted("worker", name, fmu) as host:
            start(host)
            host.start_step(0.0, h, {})
            host.finish_step()
            threads[name] = len(os.listdir(f"/proc/{host.pid}/task"))
    assert threads["tissue"] == threads["contact"], threads
