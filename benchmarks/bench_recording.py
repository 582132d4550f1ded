"""Recorder.write per-row cost vs a plain ``csv.writer`` baseline, measured side by side.

Run: ``python benchmarks/bench_recording.py``.
Target: < 15 us per row for 10 scalar float64 columns (the 1 kHz hot path), and within a small
factor of a bare buffered csv.writer that does no flushing, locking or validation.
The baseline gets the same input (a dict of 1-element numpy arrays) and writes the same text.
"""
from __future__ import annotations

import csv
import tempfile
import time
from pathlib import Path

import numpy as np

from orchestration.recording import Recorder, read_stream

N_ROWS = 20_000


def per_row_us(fn, n=N_ROWS, repeat=5) -> float:
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        fn(n)
        best = min(best, time.perf_counter() - start)
    return best / n * 1e6


def main() -> None:
    rng = np.random.default_rng(1)
    cases = {
        "10 scalar columns": [(f"s{i}", 1) for i in range(10)],
        "3 x 3-vectors + 2 scalars": [("f0", 3), ("f1", 3), ("f2", 3), ("a", 1), ("b", 1)],
        "1 array of 300 values": [("surface_force", 300)],
    }
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        print(f"{'case':<28} {'Recorder.write':>15} {'csv.writer':>11} {'ratio':>6}")
        for label, ports in cases.items():
            values = {name: rng.standard_normal(size) for name, size in ports}
            names = [name for name, _ in ports]

            rec = Recorder(tmp / "rec", flush_interval=0.2)
            rec.add_stream("c", [(name, size, None) for name, size in ports])

            def run_recorder(n, rec=rec, values=values):
                write = rec.write
                for k in range(n):
                    write("c", k * 1e-3, values)

            handle = open(tmp / "baseline.csv", "w", newline="")
            writer = csv.writer(handle, quoting=csv.QUOTE_NONNUMERIC, lineterminator="\n")

            def run_baseline(n, writer=writer, values=values, names=names):
                for k in range(n):
                    row = [k * 1e-3]
                    for name in names:
                        row.extend(values[name].tolist())
                    writer.writerow(row)

            t_rec = per_row_us(run_recorder)
            t_base = per_row_us(run_baseline)
            rec.close()
            handle.close()
            t, cols = read_stream(tmp / "rec" / "c.csv")
            assert t.size == 5 * N_ROWS, "every row written must be read back"
            print(f"{label:<28} {t_rec:>12.2f} us {t_base:>8.2f} us {t_rec / t_base:>6.2f}")


if __name__ == "__main__":
    main()
