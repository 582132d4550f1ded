"""Parameter sweeps: run one task on many parameter points, in parallel, resumably.

``run_sweep(task, points, results_path)`` calls ``task(point) -> dict`` once per point and returns
one :class:`SweepResult` per point, in the order of ``points``.

How a point runs. Every point runs in a worker *process* (never in the caller), so a point that
crashes the interpreter (segfault, ``os.abort``) or hangs cannot take the sweep down: the worker
is replaced, the point is recorded as failed ("worker process died (killed by signal SIGABRT)", "timed out
after 60 s") and the sweep goes on. Worker processes are long-lived, one per parallel slot, and
run point after point, so the task's imports and numba's cached compilation are paid once per
worker rather than once per point. A worker is a fresh interpreter (``sys.executable``, like the
"spawn" start method) prepared the way ``multiprocessing`` prepares a spawned child: same
``sys.path``, working directory, and, when the task is defined in the main script, that script
imported as ``__mp_main__`` (so scripts need the usual ``if __name__ == "__main__":`` guard).

* Locally (default) a thread per slot hands points to its worker process and waits for the answer
  with the timeout; ``workers`` defaults to ``os.cpu_count()``.
* With ``scheduler="tcp://host:port"`` each point is a dask.distributed task; the dask worker runs
  it in a worker process of its own with exactly the same code, so failures, timeouts and values
  are identical to a local run. Dask worker processes are daemonic and may not use
  ``multiprocessing``; this is why workers are plain subprocesses talking over pipes.

Results. Each finished point is appended at once to ``results_path`` as one JSON line (flushed
and fsynced), so an interrupted sweep (Ctrl-C, kill, power loss) keeps what it finished. On start,
points whose key already has an "ok" line are not run again; failed points are retried. Values
go through a JSON round trip in the worker, so a fresh result equals the same result read back.

The worker-pipe protocol uses ``multiprocessing.connection.Connection`` on raw pipe descriptors,
which is POSIX-only (Linux, macOS).
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import multiprocessing.spawn
import os
import pickle
import signal
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from multiprocessing.connection import Connection
from pathlib import Path

from tqdm import tqdm

from fmu_build.paths import REPO_ROOT
from orchestration.errors import exit_description

logger = logging.getLogger(__name__)

__all__ = ["SweepResult", "SweepConfigError", "run_sweep", "load_results", "results_table",
           "point_key"]

OK, FAILED = "ok", "failed"
_MAX_ERROR_CHARS = 400
_PACKAGE_PARENT = str(REPO_ROOT)
# How often a worker process checks that the process that started it is still alive; an
# orphaned worker (its sweep was killed) exits at once instead of finishing its point.
_ORPHAN_CHECK_S = 0.2


class SweepConfigError(ValueError):
    """A sweep was called with arguments it cannot run (bad point, task, worker count...)."""


@dataclass(frozen=True)
class SweepResult:
    """One point's outcome. ``key`` identifies the point across runs; ``error`` is one line."""

    point: dict
    key: str
    status: str
    values: dict
    error: str
    wall_time_s: float


# ---------------------------------------------------------------------------------------------
# Points and keys
# ---------------------------------------------------------------------------------------------

def point_key(point: Mapping) -> str:
    """Stable identity of a point: hash of its sorted, compact JSON (1 and 1.0 differ)."""
    text = json.dumps(point, sort_keys=True, separators=(",", ":"), ensure_ascii=True,
                      allow_nan=False)
    return hashlib.sha256(text.encode("ascii")).hexdigest()[:16]


def _scalar(value, where: str):
    # numpy scalars (np.float64, np.int64, np.bool_, 0-d arrays) become their Python value, so
    # points built with np.linspace hash and serialise like hand-written ones.
    if getattr(value, "shape", None) == () and hasattr(value, "item"):
        value = value.item()
    if value is None or isinstance(value, (bool, str, int)):
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            raise SweepConfigError(f"{where} must be a finite number (got {value!r}): a sweep "
                                   "point has to be written to JSON and hashed")
        return value
    raise SweepConfigError(f"{where} must be a str, int, float, bool or None (got "
                           f"{type(value).__name__} {value!r}): give one scalar per parameter and "
                           "vary it across points")


def _normalize_point(point, index: int) -> dict:
    if not isinstance(point, Mapping):
        raise SweepConfigError(f"points[{index}] must be a dict of parameter name -> value (got "
                               f"{type(point).__name__})")
    normalized = {}
    for name, value in point.items():
        if not isinstance(name, str):
            raise SweepConfigError(f"points[{index}] has a parameter name {name!r} of type "
                                   f"{type(name).__name__}: parameter names must be str")
        normalized[name] = _scalar(value, f"points[{index}][{name!r}]")
    return normalized


def _check_arguments(task, workers, timeout_s) -> int:
    if not callable(task):
        raise SweepConfigError(f"task must be a callable point -> dict (got {type(task).__name__})")
    if workers is None:
        workers = os.cpu_count() or 1
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise SweepConfigError(f"workers must be an int >= 1 (got {workers!r}), or None for "
                               "os.cpu_count()")
    if timeout_s is not None and not (isinstance(timeout_s, (int, float)) and timeout_s > 0
                                      and math.isfinite(timeout_s)):
        raise SweepConfigError(f"timeout_s must be a finite number of seconds > 0 (got "
                               f"{timeout_s!r}), or None for no limit")
    return workers


# ---------------------------------------------------------------------------------------------
# Results file
# ---------------------------------------------------------------------------------------------

def _result_from_record(record: dict) -> SweepResult:
    return SweepResult(point=dict(record["point"]), key=str(record["key"]),
                       status=str(record["status"]), values=dict(record["values"]),
                       error=str(record["error"]), wall_time_s=float(record["wall_time_s"]))


def load_results(path: Path | str) -> list[SweepResult]:
    """Every result line of a results file, in file order (a retried point appears once per try).

    A line that cannot be read (typically the last one, cut off when a sweep was killed while
    writing it) is skipped with a warning.
    """
    path = Path(path)
    results = []
    with path.open("r", encoding="utf-8") as stream:
        for number, line in enumerate(stream, start=1):
            if not line.strip():
                continue
            try:
                results.append(_result_from_record(json.loads(line)))
            except (ValueError, KeyError, TypeError) as exc:
                logger.warning("skipping unreadable line %d of %s (%s); probably cut off by an "
                               "interrupted sweep", number, path, _one_line(exc))
    return results


class _ResultWriter:
    """Appends one JSON line per result, durable as soon as ``write`` returns."""

    def __init__(self, path: Path):
        path.parent.mkdir(parents=True, exist_ok=True)
        # A line cut off by a kill has no newline; start on a fresh line so the next record is
        # not glued to the broken one.
        needs_newline = False
        if path.exists() and path.stat().st_size > 0:
            with path.open("rb") as stream:
                stream.seek(-1, os.SEEK_END)
                needs_newline = stream.read(1) != b"\n"
        self._stream = path.open("a", encoding="utf-8")
        if needs_newline:
            self._stream.write("\n")

    def write(self, result: SweepResult) -> None:
        self._stream.write(json.dumps(asdict(result), allow_nan=True) + "\n")
        self._stream.flush()
        os.fsync(self._stream.fileno())

    def close(self) -> None:
        self._stream.close()


def results_table(results: list[SweepResult]) -> list[dict]:
    """Flat rows for CSV writing: key, status, the point's parameters, the values, error, time.

    Nested value dicts are flattened with dotted names ("force.max"); lists become JSON text. A
    value whose name clashes with a parameter or a bookkeeping column gets the prefix "value.".
    Every row has the same columns (missing ones are None), so ``csv.DictWriter(f,
    fieldnames=rows[0])`` works.
    """
    rows = []
    for result in results:
        row = {"key": result.key, "status": result.status}
        row.update(result.point)
        for name, value in _flatten(result.values):
            if name in row or name in ("error", "wall_time_s"):
                name = f"value.{name}"
            row[name] = value
        row["error"] = result.error
        row["wall_time_s"] = result.wall_time_s
        rows.append(row)
    columns: dict[str, None] = {}
    for row in rows:
        columns.update(dict.fromkeys(row))
    # Keep error and wall time last even when a later row brings new value columns.
    for tail in ("error", "wall_time_s"):
        columns.pop(tail, None)
        columns[tail] = None
    return [{column: row.get(column) for column in columns} for row in rows]


def _flatten(values: Mapping, prefix: str = ""):
    for name, value in values.items():
        if isinstance(value, Mapping):
            yield from _flatten(value, f"{prefix}{name}.")
        elif isinstance(value, list):
            yield f"{prefix}{name}", json.dumps(value)
        else:
            yield f"{prefix}{name}", value


# ---------------------------------------------------------------------------------------------
# Worker process side
# ---------------------------------------------------------------------------------------------

def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    message = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    return message if len(message) <= _MAX_ERROR_CHARS else message[:_MAX_ERROR_CHARS - 3] + "..."


def _json_default(value):
    if hasattr(value, "tolist"):  # numpy arrays and scalars
        return value.tolist()
    raise TypeError(f"task returned a value of type {type(value).__name__}, which is not "
                    "JSON-able: return numbers, strings, lists or dicts of them")


def _outcome(status, values, error, wall_time_s, trace="") -> dict:
    return {"status": status, "values": values, "error": error, "wall_time_s": wall_time_s,
            "traceback": trace}


def _execute(payload: bytes, task_cache: dict) -> dict:
    started = time.perf_counter()
    try:
        task_bytes, point = pickle.loads(payload)
        task = task_cache.get(task_bytes)
        if task is None:
            task_cache.clear()
            task = task_cache[task_bytes] = pickle.loads(task_bytes)
        started = time.perf_counter()
        values = task(dict(point))
        if not isinstance(values, Mapping):
            raise TypeError(f"task must return a dict of results (got {type(values).__name__})")
        # The JSON round trip makes a fresh result identical to one read back from the file.
        values = json.loads(json.dumps(dict(values), default=_json_default, allow_nan=True))
        return _outcome(OK, values, "", time.perf_counter() - started)
    except (Exception, SystemExit) as exc:  # SystemExit: a task calling sys.exit() fails its point
        return _outcome(FAILED, {}, _one_line(exc), time.perf_counter() - started,
                        traceback.format_exc())


def _exit_when_orphaned(parent_pid: int) -> None:
    while True:
        if os.getppid() != parent_pid:
            os._exit(1)
        time.sleep(_ORPHAN_CHECK_S)


def _worker_main(parent_pid: int) -> None:
    """Entry point of a worker process: read (task, point) from stdin, answer on stdout."""
    # The protocol owns the original stdin/stdout; the task's prints (Python or C level) go to
    # stderr and its reads from stdin see /dev/null, so neither can corrupt the protocol.
    requests = Connection(os.dup(0), writable=False)
    replies = Connection(os.dup(1), readable=False)
    devnull = os.open(os.devnull, os.O_RDONLY)
    os.dup2(devnull, 0)
    os.close(devnull)
    os.dup2(2, 1)
    # Ctrl-C reaches the whole process group; the sweep process handles it and stops us.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_exit_when_orphaned, args=(parent_pid,), daemon=True).start()
    multiprocessing.spawn.prepare(pickle.loads(requests.recv_bytes()))
    task_cache: dict = {}
    while True:
        try:
            payload = requests.recv_bytes()
        except EOFError:
            return
        replies.send_bytes(pickle.dumps(_execute(payload, task_cache)))


_WORKER_BOOT = ("import sys; sys.path.insert(0, {path!r}); "
                "from orchestration.studies.sweep import _worker_main; _worker_main({pid})")


# ---------------------------------------------------------------------------------------------
# Sweep process side: worker processes and their pool
# ---------------------------------------------------------------------------------------------

def _preparation_data(task) -> dict:
    """What a worker needs to unpickle the task, as multiprocessing's spawn would give it."""
    data = {"sys_path": list(sys.path), "sys_argv": list(sys.argv), "dir": os.getcwd()}
    # Import the main script in the worker only when the task lives there: running a user's
    # script top level in every worker is a side effect nobody wants otherwise.
    if getattr(task, "__module__", None) == "__main__":
        main = sys.modules["__main__"]
        main_name = getattr(getattr(main, "__spec__", None), "name", None)
        main_path = getattr(main, "__file__", None)
        if main_name is not None:
            data["init_main_from_name"] = main_name
        elif main_path is not None:
            data["init_main_from_path"] = os.path.abspath(main_path)
    return data


def _death_reason(returncode: int | None) -> str:
    return f"worker process died ({exit_description(returncode)})"


class _Worker:
    """One worker process and its two pipes."""

    def __init__(self, preparation: bytes):
        command = [sys.executable, "-c",
                   _WORKER_BOOT.format(path=_PACKAGE_PARENT, pid=os.getpid())]
        self.process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self._requests = Connection(os.dup(self.process.stdin.fileno()), readable=False)
        self._replies = Connection(os.dup(self.process.stdout.fileno()), writable=False)
        self.process.stdin.close()
        self.process.stdout.close()
        self._requests.send_bytes(preparation)

    def alive(self) -> bool:
        return self.process.poll() is None

    def run(self, payload: bytes, timeout_s: float | None) -> dict:
        started = time.perf_counter()
        try:
            self._requests.send_bytes(payload)
            if not self._replies.poll(timeout_s):
                self.kill()
                return _outcome(FAILED, {}, f"timed out after {timeout_s:g} s",
                                time.perf_counter() - started)
            return pickle.loads(self._replies.recv_bytes())
        except (EOFError, OSError):
            self.kill()
            return _outcome(FAILED, {}, _death_reason(self.process.returncode),
                            time.perf_counter() - started)

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait()
        self._close_pipes()

    def stop(self, grace_s: float = 5.0) -> None:
        """Ask an idle worker to exit (end of input); kill it if it does not."""
        self._close_pipes()
        try:
            self.process.wait(grace_s)
        except subprocess.TimeoutExpired:
            self.kill()

    def _close_pipes(self) -> None:
        self._requests.close()
        self._replies.close()


class _WorkerPool:
    """Idle worker processes, handed to one thread at a time; dead ones are replaced."""

    def __init__(self, preparation: dict):
        self._preparation = pickle.dumps(preparation)
        self._lock = threading.Lock()
        self._idle: list[_Worker] = []
        self._all: set[_Worker] = set()
        self._closed = False

    def run(self, payload: bytes, timeout_s: float | None) -> dict:
        worker = self._acquire()
        try:
            return worker.run(payload, timeout_s)
        finally:
            self._release(worker)

    def _acquire(self) -> _Worker:
        with self._lock:
            if self._closed:
                raise RuntimeError("sweep worker pool is closed")
            while self._idle:
                worker = self._idle.pop()
                if worker.alive():
                    return worker
                self._all.discard(worker)
            worker = _Worker(self._preparation)
            self._all.add(worker)
            return worker

    def _release(self, worker: _Worker) -> None:
        with self._lock:
            if worker.alive() and not self._closed:
                self._idle.append(worker)
            else:
                self._all.discard(worker)

    def close(self, kill: bool = False) -> None:
        """Stop every worker: idle ones politely, busy ones (``kill=True``) at once."""
        with self._lock:
            self._closed = True
            workers, self._all, self._idle = list(self._all), set(), []
        for worker in workers:
            if kill:
                worker.kill()
            else:
                worker.stop()


# ---------------------------------------------------------------------------------------------
# Executors
# ---------------------------------------------------------------------------------------------

def _picklable_task(task) -> bytes:
    """The task pickled for local workers, or a clear error saying why it cannot be."""
    try:
        task_bytes = pickle.dumps(task)
    except Exception as exc:
        raise SweepConfigError(
            f"task {task!r} cannot be sent to worker processes ({_one_line(exc)}): define it as "
            "a top-level function (def, not lambda or nested function) in a module") from exc
    main = sys.modules.get("__main__")
    if (getattr(task, "__module__", None) == "__main__"
            and getattr(getattr(main, "__spec__", None), "name", None) is None
            and getattr(main, "__file__", None) is None):
        raise SweepConfigError(
            f"task {task!r} is defined in an interactive session, which worker processes cannot "
            "import: define it in a module (a .py file) and import it from there")
    return task_bytes


def _run_local(task, pending: dict[str, dict], workers: int, timeout_s, on_outcome) -> None:
    task_bytes = _picklable_task(task)
    pool = _WorkerPool(_preparation_data(task))
    executor = ThreadPoolExecutor(max_workers=min(workers, len(pending)),
                                  thread_name_prefix="sweep")
    finished = False
    try:
        futures = {executor.submit(pool.run, pickle.dumps((task_bytes, point)), timeout_s): key
                   for key, point in pending.items()}
        for future in as_completed(futures):
            on_outcome(futures[future], future.result())
        finished = True
    finally:
        executor.shutdown(wait=False, cancel_futures=True)
        # Interrupted: kill busy workers too, which also unblocks the threads waiting on them.
        pool.close(kill=not finished)
        executor.shutdown(wait=True)


# Worker pool of a dask worker process, created on its first sweep point.
_DASK_POOL: _WorkerPool | None = None
_DASK_POOL_LOCK = threading.Lock()


def _run_on_dask_worker(task_bytes: bytes, point: dict, timeout_s) -> dict:
    global _DASK_POOL
    with _DASK_POOL_LOCK:
        if _DASK_POOL is None:
            # The task arrives cloudpickled (by value if it came from the client's __main__), so
            # the worker process needs no main-script import.
            _DASK_POOL = _WorkerPool(_preparation_data(None))
        pool = _DASK_POOL
    return pool.run(pickle.dumps((task_bytes, point)), timeout_s)


def _close_dask_worker_pool(kill: bool = False) -> None:
    global _DASK_POOL
    with _DASK_POOL_LOCK:
        pool, _DASK_POOL = _DASK_POOL, None
    if pool is not None:
        pool.close(kill=kill)


def _run_dask(task, pending: dict[str, dict], scheduler: str, timeout_s, on_outcome) -> None:
    try:
        import cloudpickle
        from distributed import Client, as_completed as dask_as_completed
    except ImportError as exc:
        raise SweepConfigError(
            f"scheduler={scheduler!r} needs dask.distributed, which is not installed ({exc}): "
            'install it with  pip install -e ".[dask]"  or run without scheduler= for a local '
            "process pool") from exc
    task_bytes = cloudpickle.dumps(task)
    with Client(scheduler, set_as_default=False) as client:
        futures = {client.submit(_run_on_dask_worker, task_bytes, point, timeout_s,
                                 pure=False): key for key, point in pending.items()}
        finished = False
        try:
            for future in dask_as_completed(futures, loop=client.loop):
                try:
                    outcome = future.result()
                except Exception as exc:  # e.g. KilledWorker: the dask worker itself died
                    outcome = _outcome(FAILED, {}, f"dask task failed ({_one_line(exc)})", 0.0)
                on_outcome(futures[future], outcome)
            finished = True
        finally:
            if not finished:
                client.cancel(list(futures))
            try:
                client.run(_close_dask_worker_pool, kill=not finished)
            except Exception as exc:  # cleanup only; the results are already written
                logger.warning("could not stop the sweep's worker processes on the dask "
                               "workers: %s", _one_line(exc))


# ---------------------------------------------------------------------------------------------
# The sweep
# ---------------------------------------------------------------------------------------------

def run_sweep(task: Callable[[dict], dict], points: list[dict], results_path: Path | str, *,
              workers: int | None = None, scheduler: str | None = None, progress: bool = True,
              description: str = "sweep", timeout_s: float | None = None) -> list[SweepResult]:
    """Run ``task(point)`` for every point; return results in the order of ``points``.

    ``task`` must be picklable (a top-level function) and return a dict of JSON-able values.
    Points are dicts of scalar parameters; a point listed twice runs once. ``workers`` (default
    ``os.cpu_count()``) bounds local parallelism and is ignored with ``scheduler``, where the
    dask cluster decides. ``timeout_s`` bounds one point's run time. Points with an "ok" line in
    ``results_path`` are not run again.
    """
    workers = _check_arguments(task, workers, timeout_s)
    normalized = [_normalize_point(point, index) for index, point in enumerate(points)]
    keys = [point_key(point) for point in normalized]
    path = Path(results_path)

    results: dict[str, SweepResult] = {}
    if path.exists():
        wanted = set(keys)
        for result in load_results(path):
            if result.status == OK and result.key in wanted:
                results[result.key] = result
    pending = {key: point for key, point in zip(keys, normalized) if key not in results}
    n_unique = len(set(keys))
    if results:
        logger.info("%s: %d of %d points already done in %s, running the other %d", description,
                    len(results), n_unique, path, len(pending))

    writer = _ResultWriter(path)
    bar = tqdm(total=n_unique, initial=len(results), desc=description, unit="point",
               disable=not progress)
    n_failed = 0

    def on_outcome(key: str, outcome: dict) -> None:
        nonlocal n_failed
        result = SweepResult(point=pending[key], key=key, status=outcome["status"],
                             values=outcome["values"], error=outcome["error"],
                             wall_time_s=float(outcome["wall_time_s"]))
        writer.write(result)
        results[key] = result
        if result.status != OK:
            n_failed += 1
            logger.warning("%s: point %s failed: %s", description, result.point, result.error)
            if outcome.get("traceback"):
                logger.debug("%s: traceback of point %s:\n%s", description, result.point,
                             outcome["traceback"])
        bar.set_postfix(failed=n_failed, refresh=False)
        bar.update(1)

    try:
        if pending and scheduler is not None:
            _run_dask(task, pending, scheduler, timeout_s, on_outcome)
        elif pending:
            _run_local(task, pending, workers, timeout_s, on_outcome)
    finally:
        bar.close()
        writer.close()
    return [results[key] for key in keys]
