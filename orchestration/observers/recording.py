"""The recording observer: the observed ports of each component into its stream (CSV), surfaces into
VTU series."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from orchestration.scene.model import Scene
from orchestration.observers.base import Observer


class Recording(Observer):
    """CSV rows of the scene's ``[record]`` ports and the surface time series (VTU + PVD)."""

    def __init__(self, scene: Scene, out_dir: Path, *, surfaces: bool = True):
        self.scene = scene
        self.out_dir = Path(out_dir)
        self.surfaces = list(scene.surfaces) if surfaces else []
        self.recorder = None
        self._recorded = {name: list(ports) for name, ports in scene.record.items()}
        # Surface frames and the CSV rows' text are written by processes of their own, started
        # now: their start-up (half a second for the surface writer's imports) runs beside the
        # FMUs' set-up, not into the first steps.
        self._surface_writer = self._row_writer = None
        if self.surfaces:
            from orchestration.observers.surface_writer import SurfaceWriter

            self._surface_writer = SurfaceWriter(self.out_dir)
        if self._recorded:
            from orchestration.observers.row_writer import RowWriter

            self._row_writer = RowWriter()

    def ports(self, component: str) -> list[str]:
        ports = list(self._recorded.get(component, []))
        for surface in self.surfaces:
            if surface.component == component:
                ports += [surface.positions, *surface.point_data]
        return ports

    def initializing(self, algorithm) -> None:
        from orchestration.observers.recorder import Recorder

        self.seconds = algorithm.seconds
        self.base = algorithm.base
        self.recorder = Recorder(self.out_dir, surface_writer=self._surface_writer, row_writer=self._row_writer)
        for name, ports in self._recorded.items():
            spec = self.scene.components[name]
            self.recorder.add_stream(name, [(p, spec.ports[p].size, spec.ports[p].unit) for p in ports])

    def initialized(self, algorithm) -> None:
        for surface in self.surfaces:
            values = algorithm.get_values(surface.component, [surface.triangles, surface.positions,
                                                                *surface.point_data])
            triangles = np.asarray(values[surface.triangles]).reshape(-1, 3).astype(np.int64)
            self.recorder.add_surface_series(surface.name, triangles)
            self._write_surface(surface, 0, values)

    def stepped(self, comp, tick: int, outputs) -> None:
        if comp.name in self._recorded:
            self.recorder.write(comp.name, self.seconds(tick), outputs)
        if tick:
            for surface in self.surfaces:
                if surface.component == comp.name and comp.steps % surface.every == 0:
                    self._write_surface(surface, tick, outputs)

    def stepped_block(self, comp, ticks: list[int], outputs: dict[str, np.ndarray], first_step: int) -> None:
        """``stepped`` for steps ``first_step + 1, ...`` ending at ``ticks``; ``outputs[port]`` has a row per step."""
        if comp.name in self._recorded:
            # int64 / int: correctly rounded below 2**53, the same floats as self.seconds
            self.recorder.write_rows(comp.name, np.array(ticks, dtype=np.int64) / self.base, outputs)
        for surface in self.surfaces:
            if surface.component == comp.name:
                for i, tick in enumerate(ticks):
                    if tick and (first_step + i + 1) % surface.every == 0:
                        self._write_surface(surface, tick, {name: values[i] for name, values in outputs.items()})

    def _write_surface(self, surface, tick: int, outputs) -> None:
        positions = np.asarray(outputs[surface.positions]).reshape(-1, 3)
        point_data = {name: np.asarray(outputs[name]).reshape(positions.shape[0], -1).squeeze()
                      for name in surface.point_data}
        self.recorder.write_surface(surface.name, self.seconds(tick), positions, point_data)

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.close()  # closes the writer processes too, once everything is on disk
        else:  # the run ended before recording began
            for writer in (self._surface_writer, self._row_writer):
                if writer is not None:
                    writer.close()

    @property
    def surface_errors(self) -> list[str]:
        """What the surface writer could not write (known once closed)."""
        return self.recorder.surface_errors if self.recorder is not None else []

    @property
    def row_errors(self) -> list[str]:
        """What the row writer could not write (known once closed)."""
        return self.recorder.row_errors if self.recorder is not None else []

    @property
    def writers(self) -> list:
        """The run's writer processes that were started (surface writer, row writer)."""
        return [writer for writer in (self._surface_writer, self._row_writer) if writer is not None]

    @property
    def processes(self) -> dict[str, int]:
        """Helper processes of the run by name (the writers), for the real-time pacing."""
        return {writer.label: writer.pid for writer in self.writers}

    @property
    def files(self) -> dict:
        return self.recorder.files if self.recorder is not None else {}
