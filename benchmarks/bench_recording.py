"""Recorder.write per-row cost vs a plain ``csv.writer`` baseline, measured side by side.

Three ways to record the same rows: the recorder making the CSV text in this process (at each
flush), the recorder handing its row blocks to a row writer process that makes the text (what a
run does), and a bare buffered ``csv.writer`` that does no flushing, locking or validation. For
each, per row: the CPU time of this process (every thread: what the 1 kHz loop's process pays;
the row writer's own process is not counted) and the wall time until every row is in the file.

Run: ``python benchmarks/bench_recording.py``.
Target: < 15 us of this process's CPU per row for 10 scalar float64 columns (the 1 kHz hot path).
The baseline gets the same input (a dict of numpy arrays) and writes the same text.
"""
from __future__ import annotations

import csv
import tempfile
import time
from pathlib import Path

import numpy as np

from orchestration.observers.recorder import Recorder, read_stream
from orchestration.observers.row_writer import RowWriter

N_ROWS = 20_000


def timed(n: int, write, close) -> tuple[float, float]:
    """(this process's CPU us per row, wall us per row), n writes until closed."""
    cpu, wall = time.process_time(), time.perf_counter()
    for k in range(n):
        write(k * 1e-3)
    close()
    return (time.process_time() - cpu) / n * 1e6, (time.perf_counter() - wall) / n * 1e6


def main() -> None:
    rng = np.random.default_rng(1)
    cases = {
        "10 scalar columns": [(f"s{i}", 1) for i in range(10)],
        "3 x 3-vectors + 2 scalars": [("f0", 3), ("f1", 3), ("f2", 3), ("a", 1), ("b", 1)],
        "1 array of 300 values": [("surface_force", 300)],
    }
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        print(f"us per row, this process's CPU / wall until in the file ({N_ROWS} rows)")
        print(f"{'case':<28} {'text here':>17} {'row writer':>17} {'csv.writer':>17}")
        for case, (label, ports) in enumerate(cases.items()):
            values = {name: rng.standard_normal(size) for name, size in ports}
            names = [name for name, _ in ports]
            results = []
            for kind in ("here", "writer"):
                out = tmp / f"{kind}-{case}"
                rec = Recorder(out, flush_interval=0.2, row_writer=RowWriter() if kind == "writer" else None)
                rec.add_stream("c", [(name, size, None) for name, size in ports])
                results.append(timed(N_ROWS, lambda t, rec=rec: rec.write("c", t, values), rec.close))
                t, _ = read_stream(out / "c.csv")
                assert t.size == N_ROWS, "every row written must be read back"
            handle = open(tmp / "baseline.csv", "w", newline="")
            writer = csv.writer(handle, quoting=csv.QUOTE_NONNUMERIC, lineterminator="\n")

            def baseline(t, writer=writer, values=values, names=names):
                row = [t]
                for name in names:
                    row.extend(values[name].tolist())
                writer.writerow(row)

            results.append(timed(N_ROWS, baseline, handle.close))
            print(f"{label:<28} " + " ".join(f"{a:7.2f} / {b:7.2f}" for a, b in results))


if __name__ == "__main__":
    main()
