"""Surface frames (VTU) written by a process of their own, beside the run.

Writing one frame of the default wall (2,688 points, 5,376 triangles) takes about 8 ms, most of it
meshio's zlib compression: every third tissue frame, that is 20-40 % of the default scene's wall
time, and a stall of 8 ms in the 1 kHz loop (with ``--realtime``, about 70 % of the missed haptic
deadlines of the default scene were these). The recorder hands each frame to this
process instead (one pipe message of the positions) and goes on.

Nothing is lost: frames are written in the order they were sent, each file and the rewritten
``.pvd`` atomically (:func:`write_frame`); :meth:`SurfaceWriter.close` waits until every frame is
on disk, and a run's process that dies leaves the writer to write what it was sent
(:mod:`.helper_process`). A writer process that dies or is killed (it made no progress within its
deadline) leaves the frames to this process from then on, written by the thread that fed the
writer (so the 1 kHz loop still does not wait for them): only the frames the writer had taken and
not yet written are missing, the ``.pvd`` lists the frames that are on disk, and the recorder's
check at the end (:meth:`~.recording.Recorder.close`) says which are missing.
"""
from __future__ import annotations

import logging
import os
import queue
import threading
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from orchestration.observers.helper_process import HelperProcess, begin_helper, serve

#: The helper's name in messages; its process runs as "surface-writer".
LABEL = "surface writer"

log = logging.getLogger(__name__)


def write_frame(frame: Path, pvd: Path, out_dir: Path, frames: list, t: float, positions: np.ndarray,
                triangles: np.ndarray, point_data: dict) -> None:
    """Write ``frame`` (VTU) and rewrite ``pvd`` to list ``frames`` plus this one, each atomically."""
    import meshio  # only runs that record surfaces pay for the import

    tmp = frame.with_name(f".{frame.name}.tmp")
    try:
        meshio.write(tmp, meshio.Mesh(positions, [("triangle", triangles)], point_data=point_data), file_format="vtu")
        os.replace(tmp, frame)  # the .pvd never names a half-written frame
    except BaseException:
        _remove(tmp)  # a full volume: no half-written frame left to take the space the next might find
        raise
    frames.append((t, frame))
    write_pvd(pvd, out_dir, frames)


def write_pvd(pvd: Path, out_dir: Path, frames: list) -> None:
    """The ParaView collection of ``frames`` ((time, path) pairs), written atomically."""
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    collection = ET.SubElement(root, "Collection")
    for t, frame in frames:
        ET.SubElement(collection, "DataSet", timestep=repr(t), group="", part="0",
                      file=frame.relative_to(out_dir).as_posix())
    ET.indent(root)
    tmp = pvd.with_name(f".{pvd.name}.tmp")
    try:
        tmp.write_text('<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n", encoding="utf-8")
        os.replace(tmp, pvd)
    except BaseException:
        _remove(tmp)
        raise


def _remove(path: Path) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def _yield_to_the_run() -> None:
    """Run only when a CPU would otherwise idle (Linux SCHED_IDLE; elsewhere the lowest priority):
    the writer never preempts the 1 kHz loop or the tissue worker, it uses the time they leave."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        return
    except (AttributeError, OSError):
        pass
    try:
        os.nice(19)
    except OSError:
        pass


class SurfaceWriter:
    """The writer process: ``add_series`` once per surface, ``write`` per frame, ``close`` at the end.

    Validation stays with the caller (the recorder); errors of the writer itself (a full disk) are
    logged by it as they happen, told at once through ``on_notice`` (the first of each surface) and
    returned by ``close``.
    """

    label = LABEL

    def __init__(self, out_dir: Path):
        self.out_dir = Path(out_dir)
        self._helper = HelperProcess(LABEL, _serve, str(out_dir))
        # A frame (64 KB for the default wall) fills the pipe: sending it blocks until the writer
        # reads, and the writer runs only on an idle CPU. Sent from the run's thread, the 1 kHz loop
        # would wait in these sends for a fifth of its time; this thread waits instead (the write
        # releases the GIL).
        self._outbox: queue.SimpleQueue = queue.SimpleQueue()
        self._series: dict[str, tuple[np.ndarray, Path]] = {}
        #: frames handed to the writer process, per surface: (time, path)
        self._sent: dict[str, list] = {}
        #: once the writer process is gone: the frames on disk per surface, written on by this process
        self._here: dict[str, list] | None = None
        #: errors of the frames this process wrote itself
        self._errors: list[str] = []
        self._noticed: set[str] = set()
        self._sender = threading.Thread(target=self._send_all, name="surface-sender", daemon=True)
        self._sender.start()
        self._closed = False

    @property
    def pid(self) -> int:
        return self._helper.pid

    @property
    def helper(self) -> HelperProcess:
        """The process: its deadline (``timeout``), its notices (``on_notice``, ``poll``)."""
        return self._helper

    def add_series(self, name: str, triangles: np.ndarray, pvd: Path) -> None:
        self._series[name] = (triangles, Path(pvd))
        self._sent[name] = []
        self._outbox.put(("series", name, triangles, str(pvd)))

    def write(self, name: str, frame: Path, t: float, positions: np.ndarray, point_data: dict) -> None:
        """Queue one frame (the arrays are the writer's from now on: pass copies)."""
        self._outbox.put(("frame", name, str(frame), t, positions, point_data))

    def _send_all(self) -> None:
        while True:
            message = self._outbox.get()
            if message is None:
                return
            if self._here is None:
                if self._helper.send(message):
                    if message[0] == "frame":
                        self._sent[message[1]].append((message[3], Path(message[2])))
                    continue
                self._take_over()
            self._write_here(message)

    def _take_over(self) -> None:
        """The writer process is gone: write the frames here from now on, each surface's ``.pvd``
        listing the frames that are on disk (those the writer had taken and not written are not)."""
        log.error("the %s process is gone (%s): this process writes the surface frames from now on",
                  self.label, self._helper.exit_description())
        self._here = {}
        for name, sent in self._sent.items():
            frames = self._here[name] = [(t, frame) for t, frame in sent if frame.exists()]
            try:
                write_pvd(self._series[name][1], self.out_dir, frames)
            except OSError as exc:
                self._failed(name, self._series[name][1], exc)

    def _write_here(self, message: tuple) -> None:
        if message[0] == "series":
            self._here[message[1]] = []
            return
        _, name, frame, t, positions, point_data = message
        triangles, pvd = self._series[name]
        try:
            write_frame(Path(frame), pvd, self.out_dir, self._here[name], t, positions, triangles, point_data)
        except Exception as exc:
            self._failed(name, Path(frame), exc)

    def _failed(self, name: str, path: Path, exc: Exception) -> None:
        self._errors.append(f"{name}: {type(exc).__name__}: {exc}")
        log.error("%s: %s", LABEL, self._errors[-1])
        if name in self._noticed or self._helper.on_notice is None:
            return
        self._noticed.add(name)
        self._helper.on_notice({"name": name, "error": self._errors[-1], **_notice(path, exc, len(self._here[name]))})

    def close(self) -> list[str]:
        """Wait until every frame sent is written; the writer's errors, if any. Idempotent."""
        if self._closed:
            return []
        self._closed = True
        self._outbox.put(None)
        self._sender.join()  # bounded: a send waits at most the writer's deadline, then frames are written here
        errors = self._helper.close("frame")
        if self._here is not None:
            errors.append("the run's own process wrote the frames from then on")
        return errors + self._errors


def _notice(path: Path, exc: Exception, frames_kept: int) -> dict:
    """What the run is told when a frame cannot be written: which file, why, how many frames are kept."""
    return {"kind": "frame", "path": str(path), "errno": getattr(exc, "errno", None),
            "reason": getattr(exc, "strerror", None) or str(exc), "frames_kept": frames_kept}


def _serve(conn, out_dir: str) -> None:
    """The writer's loop: frames in the order sent, until "close" or until the run's process is gone."""
    begin_helper(LABEL)
    _yield_to_the_run()
    import meshio  # noqa: F401  (now, not at the first frame, which the run is waiting to see written)

    out = Path(out_dir)
    series: dict[str, tuple] = {}

    def handle(message: tuple) -> None:
        if message[0] == "series":
            _, name, triangles, pvd = message
            series[name] = (triangles, Path(pvd), [])
        else:
            _, name, frame, t, positions, point_data = message
            triangles, pvd, frames = series[name]
            try:
                write_frame(Path(frame), pvd, out, frames, t, positions, triangles, point_data)
            except Exception as exc:
                exc.notice = _notice(Path(frame), exc, len(frames))
                raise

    serve(conn, LABEL, handle)
