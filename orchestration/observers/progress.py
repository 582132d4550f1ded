"""The progress bar of a run (tqdm), in simulated seconds."""
from __future__ import annotations

from orchestration.scene.model import Scene
from orchestration.observers.base import Observer


class Progress(Observer):
    """A tqdm bar in simulated seconds (shown after one second of wall time)."""

    def __init__(self, scene: Scene, duration: float, enabled: bool = True):
        self.scene, self.duration, self.enabled = scene, float(duration), enabled
        self.bar = None
        self._shown = 0

    def started(self, algorithm) -> None:
        from tqdm import tqdm

        self.seconds = algorithm.seconds
        self._every = max(1, algorithm.base // 100)
        self._end = algorithm.end
        self.bar = tqdm(total=self.duration, desc=self.scene.name, unit="s", delay=1.0, disable=not self.enabled,
                        bar_format="{l_bar}{bar}| {n:.3f}/{total:.3f} s sim [{elapsed}<{remaining}]")

    def advance(self, tick: int) -> None:
        if self.bar is not None and (tick - self._shown >= self._every or tick >= self._end):
            self.bar.update(self.seconds(tick) - self.bar.n)
            self._shown = tick

    def finished(self, algorithm) -> None:
        if self.bar is not None:
            self.bar.close()
