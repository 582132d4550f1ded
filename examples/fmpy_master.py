"""Compose the three FMUs in your own master: a plain FMPy loop that follows their coupling contract.

What a system engineer writes to run the project's default scene without its orchestrator. Each
FMU states its contract in ``documentation/coupling.json`` (and, for people,
``documentation/index.html``): which input comes from which output, at what rate, with which
transition and ordering, and the rules of the frame handshake and the 30 Hz average. This master
wires the FMUs from those files; the parameters and the operator's scripted insertion come from the
scene file. It writes ``contact.csv`` and ``catheter.csv`` as the orchestrator does, and gives the
same numbers (``tests/test_fmpy_master.py`` compares them).

    .venv/bin/python examples/fmpy_master.py                       # 4 s of the default scene into ./fmpy_master/
    .venv/bin/python examples/fmpy_master.py --duration 2 --out /tmp/run

The FMUs are in ``fmus/`` after ``python -m orchestration build`` (or the README's first command).
"""
from __future__ import annotations

import argparse
import bisect
import csv
import json
import math
import tomllib
from fractions import Fraction
from pathlib import Path
from tempfile import TemporaryDirectory

import numpy as np
from fmpy import extract, read_model_description
from fmpy.fmi3 import FMU3Slave

REPO = Path(__file__).resolve().parent.parent
#: what the orchestrator records of the default scene, compared by the test
RECORD = {"Contact": ["tool_force", "tip_force", "penetration_depth", "contact_count", "contact_energy",
                      "passivity_energy"],
          "Catheter": ["tip_position", "bend_angle", "actuator_command", "tip_force_magnitude",
                       "advised_insertion_scale", "effort_warning"]}


class Fmu:
    """One FMU instance with its variables by name; arrays sized by the structural parameters set."""

    def __init__(self, path: Path, folder: Path):
        self.name = read_model_description(str(path)).modelName
        self.folder = Path(extract(str(path), str(folder / self.name)))
        self.md = read_model_description(str(self.folder))
        self.variables = {v.name: v for v in self.md.modelVariables}
        self.contract = json.loads((self.folder / "documentation" / "coupling.json").read_text())
        self.slave = FMU3Slave(guid=self.md.guid, unzipDirectory=str(self.folder),
                               modelIdentifier=self.md.coSimulation.modelIdentifier, instanceName=self.name)
        self.slave.instantiate()
        self.sizes: dict[str, int] = {}

    def size(self, name: str) -> int:
        size = 1
        for dimension in self.variables[name].dimensions:
            size *= int(self.sizes.get(dimension.variable.name, dimension.variable.start)
                        if dimension.variable is not None else dimension.start)
        return size

    def set(self, name: str, value) -> None:
        variable = self.variables[name]
        values = np.ravel(value).tolist()
        if variable.type == "Float64":
            self.slave.setFloat64([variable.valueReference], [float(x) for x in values])
        elif variable.type == "String":
            self.slave.setString([variable.valueReference], [str(x) for x in values])
        elif variable.type == "Boolean":
            self.slave.setBoolean([variable.valueReference], [bool(x) for x in values])
        else:  # Int32, UInt64
            setter = self.slave.setUInt64 if variable.type == "UInt64" else self.slave.setInt32
            setter([variable.valueReference], [int(x) for x in values])

    def get(self, name: str) -> np.ndarray:
        variable = self.variables[name]
        getter = {"Float64": self.slave.getFloat64, "Int32": self.slave.getInt32,
                  "Boolean": self.slave.getBoolean}[variable.type]
        return np.array(getter([variable.valueReference], nValues=self.size(name)), dtype=np.float64)

    def configure(self, parameters: dict) -> None:
        """Rule 'modes': structural parameters in Configuration Mode, the others after it."""
        structural = {k: v for k, v in parameters.items() if self.variables[k].causality == "structuralParameter"}
        if structural:
            self.slave.enterConfigurationMode()
            for name, value in structural.items():
                self.set(name, value)
                self.sizes[name] = int(value)
            self.slave.exitConfigurationMode()
        for name, value in parameters.items():
            if name not in structural:
                self.set(name, value)


def operator(source: dict):
    """The scene's scripted operator: piecewise linear in time, evaluated at any time as the
    orchestrator's source does, (1 - w) v0 + w v1 (``np.interp``'s formula differs in the last bit)."""
    times = [float(x) for x in source["times"]]
    outputs = {name: [float(x) for x in values] for name, values in source["outputs"].items()}

    def at(t: float) -> dict[str, float]:
        i = bisect.bisect_right(times, t)  # times[i - 1] <= t < times[i]
        if i == 0 or i == len(times):
            return {name: values[max(i - 1, 0)] for name, values in outputs.items()}
        w = (t - times[i - 1]) / (times[i] - times[i - 1])
        return {name: (1.0 - w) * values[i - 1] + w * values[i] for name, values in outputs.items()}
    return at


def run(scene_file: Path, fmu_dir: Path, duration: Fraction, out: Path) -> None:
    scene = tomllib.loads(scene_file.read_text())
    at = operator(scene["source"]["operator"])
    with TemporaryDirectory() as folder:
        fmus = {name: Fmu(fmu_dir / f"{name}.fmu", Path(folder)) for name in ("Tissue", "Catheter", "Contact")}
        tissue, catheter, contact = fmus["Tissue"], fmus["Catheter"], fmus["Contact"]
        # the links as the FMUs state them: consumer -> [(input, producer, output, transition, ordering)]
        links = {name: [] for name in fmus}
        for link in contact.contract["inputs"] + catheter.contract["inputs"] + tissue.contract["inputs"]:
            (producer, output), (consumer, port) = link["source"].split("."), link["target"].split(".")
            links[consumer].append((port, producer, output, link["transition"], link["ordering"]))
        steps = {name: Fraction(step) for name, step in contact.contract["steps"].items()}
        h, big_h = steps["Contact"], steps["Tissue"]
        assert steps["Catheter"] == h, "this loop steps Catheter and Contact together"
        for name, fmu in fmus.items():
            fmu.configure(scene["fmu"][name.lower()].get("parameters", {}))

        # Rule 'initialization': Tissue, Catheter, Contact, each with the outputs of those before it.
        latest = {}  # producer -> {output: its latest sample}

        def take(name):  # the outputs of `name` that another FMU reads, as they are now
            read = {out for consumer in links.values() for (_, producer, out, _, _) in consumer if producer == name}
            latest[name] = {o: fmus[name].get(o) for o in read}

        tissue.slave.enterInitializationMode(startTime=0.0)
        tissue.slave.exitInitializationMode()
        take("Tissue")
        catheter.slave.enterInitializationMode(startTime=0.0)
        for port, value in at(0.0).items():
            catheter.set(port, value)
        catheter.slave.exitInitializationMode()
        take("Catheter")
        contact.slave.enterInitializationMode(startTime=0.0)
        for port, producer, output, _, _ in links["Contact"]:
            contact.set(port, latest[producer][output])  # surface_triangles (rule 'triangles'), frame 0, tool
        contact.slave.exitInitializationMode()
        take("Contact")

        # Rule 'average': window j of the tissue step [j H, (j + 1) H] holds Contact's samples in
        # ((j - 1) H, j H]: a running sum begun with the first sample, divided by their number.
        windows: dict[int, list] = {}
        patch_at: dict[int, np.ndarray] = {}

        def contact_sample(m: int) -> None:  # Contact's outputs at m h
            j = math.ceil(m * h / big_h)
            force = latest["Contact"]["tissue_contact_force"]
            if j in windows:
                windows[j][0] += force
                windows[j][1] += 1
            else:
                windows[j] = [force.copy(), 1]
            patch_at[j] = latest["Contact"]["patch_nodes"]  # the latest at or before j H (hold, jacobi)

        contact_sample(0)
        rows = {name: [[0.0, *np.concatenate([fmus[name].get(c) for c in columns])]]
                for name, columns in RECORD.items()}
        n = int(duration / h)
        frames_done = 0  # tissue steps done; step j makes the frame Contact sees from (j + 1) H
        for k in range(n):
            t = k * h
            # Rule 'frame': every tissue frame finished at or before t, before Contact's step [t, t + h]
            while (frames_done + 1) * big_h <= t:
                j = frames_done
                total, count = windows.pop(j)
                tissue.set("contact_force", total / count)
                tissue.set("patch_nodes", patch_at.pop(j))
                tissue.slave.doStep(currentCommunicationPoint=float(j * big_h), communicationStepSize=float(big_h))
                take("Tissue")
                frame_ports = [(port, output) for port, producer, output, _, _ in links["Contact"]
                               if producer == "Tissue" and output != "surface_triangles"]
                for port, output in sorted(frame_ports, key=lambda p: p[0] == "tissue_frame"):  # the counter last
                    contact.set(port, latest["Tissue"][output])
                frames_done += 1
            # Catheter: the operator at t + h (gauss-seidel), Contact's outputs at t (jacobi)
            for port, value in at(float(t + h)).items():
                catheter.set(port, value)
            for port, producer, output, _, _ in links["Catheter"]:
                if producer == "Contact":
                    catheter.set(port, latest["Contact"][output])
            catheter.slave.doStep(currentCommunicationPoint=float(t), communicationStepSize=float(h))
            take("Catheter")
            # Contact: the catheter's shape at t + h (gauss-seidel: Catheter stepped first)
            contact.set("tool_positions", latest["Catheter"]["centerline_positions"])
            contact.slave.doStep(currentCommunicationPoint=float(t), communicationStepSize=float(h))
            take("Contact")
            contact_sample(k + 1)
            for name, columns in RECORD.items():
                rows[name].append([float(t + h), *np.concatenate([fmus[name].get(c) for c in columns])])
        for fmu in fmus.values():
            fmu.slave.terminate()
            fmu.slave.freeInstance()
    out.mkdir(parents=True, exist_ok=True)
    for name, columns in RECORD.items():
        header = ["time"] + [f"{c}[{i}]" if fmus[name].size(c) > 1 else c
                             for c in columns for i in range(fmus[name].size(c))]
        with open(out / f"{name.lower()}.csv", "w", newline="") as f:
            writer = csv.writer(f, quoting=csv.QUOTE_NONNUMERIC)
            writer.writerow(header)
            writer.writerows(rows[name])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, default=REPO / "scenes" / "aaa_endovascular.toml")
    parser.add_argument("--fmus", type=Path, default=REPO / "fmus", help="the folder with the three .fmu files")
    parser.add_argument("--duration", type=Fraction, default=Fraction(4), help="simulated seconds (default 4)")
    parser.add_argument("--out", type=Path, default=Path("fmpy_master"))
    args = parser.parse_args()
    run(args.scene, args.fmus, args.duration, args.out)
    print(f"wrote {args.out / 'contact.csv'} and {args.out / 'catheter.csv'}")


if __name__ == "__main__":
    main()
