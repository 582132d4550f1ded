"""The main job: the default AAA simulation (``python -m orchestration run``).

Until the multirate orchestrator and its scenes land, this runs the Tissue FMU alone on the
default AAA mesh: a scripted probe presses on the aneurysm sac (force ramped up, held, then
released), the FMU is stepped at its 30 Hz communication step, results stream to a CSV file as
they are produced, and a summary is printed and saved as JSON.
"""
from __future__ import annotations

import csv
import json
import logging
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from .build import DEFAULT_FMU_DIR, build_fmu, fmu_is_stale

logger = logging.getLogger(__name__)

#: Probe load on the sac: peak total force (N), contact patch radius (m), ramp/hold/release (s).
PEAK_FORCE = 0.5
PATCH_RADIUS = 0.006
RAMP, HOLD = 0.5, 0.8

RECORDED = ("strain_energy", "kinetic_energy", "max_strain", "nonlinear_fraction",
            "solver_iterations", "solver_residual")


class SimulationError(RuntimeError):
    """An FMU call failed; the message names the FMU, the call and the simulated time."""


def probe_force_profile(t: float) -> float:
    """Total probe force (N) at time t: linear ramp, hold, linear release."""
    if t < RAMP:
        return PEAK_FORCE * t / RAMP
    if t < RAMP + HOLD:
        return PEAK_FORCE
    return PEAK_FORCE * max(0.0, 1.0 - (t - RAMP - HOLD) / RAMP)


def _patch_weights(surface_positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outer-wall sac nodes under the probe, with the inward radial direction of each."""
    centre_z = 0.5 * (surface_positions[:, 2].min() + surface_positions[:, 2].max())
    radial = surface_positions[:, :2]
    r = np.linalg.norm(radial, axis=1)
    # the probe touches the outer wall at +x, at mid-sac
    contact = np.array([r.max(), 0.0, centre_z])
    outer = r > 0.98 * r.max()
    near = outer & (np.linalg.norm(surface_positions - contact, axis=1) < PATCH_RADIUS)
    if not near.any():
        raise SimulationError("the probe patch found no surface node: is this the AAA mesh?")
    direction = np.zeros_like(surface_positions)
    direction[near, :2] = -radial[near] / r[near, None]
    return near, direction


def run_main_job(args) -> int:
    from fmpy import extract, read_model_description
    from fmpy.fmi3 import FMU3Slave
    from tqdm import tqdm

    quiet = bool(getattr(args, "quiet", False))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    fmu = DEFAULT_FMU_DIR / "Tissue.fmu"
    if fmu_is_stale("Tissue"):
        if not quiet:
            print("building fmus/Tissue.fmu ...")
        build_fmu("Tissue")

    md = read_model_description(str(fmu))
    variables = {v.name: v for v in md.modelVariables}
    step = float(md.defaultExperiment.stepSize)
    n_steps = int(round(args.duration / step))
    unzipdir = extract(str(fmu), tempfile.mkdtemp(prefix="aaa_tissue_"))
    messages: list[str] = []

    def log_message(env, status, category, message):
        text = message.decode() if isinstance(message, bytes) else str(message)
        messages.append(text)
        logger.log(logging.ERROR if status >= 3 else logging.WARNING, "Tissue: %s", text)

    def vr(name):
        return [variables[name].valueReference]

    def size(name):
        return int(np.prod(variables[name].shape))

    slave = FMU3Slave(guid=md.guid, unzipDirectory=unzipdir, modelIdentifier="Tissue", instanceName="tissue")
    started = time.perf_counter()
    try:
        slave.instantiate(loggingOn=True, logMessage=log_message)
        slave.enterInitializationMode()
        slave.exitInitializationMode()
        rest = np.array(slave.getFloat64(vr("surface_positions"), nValues=size("surface_positions"))).reshape(-1, 3)
        near, direction = _patch_weights(rest)
        per_node = direction / near.sum()
        loaded = time.perf_counter()
        csv_path = out / "tissue.csv"
        peak = {"max_displacement_m": 0.0, "strain_energy_J": 0.0, "max_strain": 0.0, "solver_iterations": 0,
                "nonlinear_fraction": 0.0}
        with open(csv_path, "w", newline="") as handle:
            writer = csv.writer(handle, quoting=csv.QUOTE_NONNUMERIC)
            writer.writerow(["time", "probe_force", "max_displacement", *RECORDED])
            for k in tqdm(range(n_steps), desc="AAA tissue", unit="frame", disable=quiet):
                t = k * step
                total = probe_force_profile(t)
                slave.setFloat64(vr("contact_force"), (per_node * total).ravel().tolist())
                try:
                    slave.doStep(t, step)
                except Exception as exc:
                    reason = messages[-1] if messages else str(exc)
                    raise SimulationError(f"Tissue: fmi3DoStep failed at t = {t:.4f} s: {reason}") from None
                positions = np.array(slave.getFloat64(vr("surface_positions"), nValues=size("surface_positions")))
                displacement = float(np.max(np.linalg.norm(positions.reshape(-1, 3) - rest, axis=1)))
                values = [slave.getFloat64(vr(n))[0] if variables[n].type == "Float64" else slave.getInt32(vr(n))[0]
                          for n in RECORDED]
                writer.writerow([t + step, total, displacement, *values])
                handle.flush()
                peak["max_displacement_m"] = max(peak["max_displacement_m"], displacement)
                peak["strain_energy_J"] = max(peak["strain_energy_J"], values[0])
                peak["max_strain"] = max(peak["max_strain"], values[2])
                peak["nonlinear_fraction"] = max(peak["nonlinear_fraction"], values[3])
                peak["solver_iterations"] = max(peak["solver_iterations"], int(values[4]))
        slave.terminate()
    except SimulationError as exc:
        print(f"error: {exc}\nresults up to the failure are in {out}")
        return 1
    finally:
        try:
            slave.freeInstance()
        except Exception:
            pass
        shutil.rmtree(unzipdir, ignore_errors=True)
    wall = time.perf_counter() - loaded
    load_time = loaded - started
    simulated = n_steps * step
    summary = {
        "scene": "AAA wall under a probe (Tissue FMU alone; the full scene needs the orchestrator)",
        "simulated_time_s": simulated,
        "load_time_s": round(load_time, 3),
        "stepping_wall_time_s": round(wall, 3),
        "real_time_factor": round(simulated / wall, 3),
        "peak_probe_force_N": PEAK_FORCE,
        **{k: (round(v, 9) if isinstance(v, float) else v) for k, v in peak.items()},
        "warnings": messages,
        "results": str(csv_path),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    if not quiet:
        print(f"\nAAA tissue under a {PEAK_FORCE} N probe, {simulated:.2f} s simulated in {wall:.1f} s "
              f"(real-time factor {summary['real_time_factor']:.2f}; FMU load {load_time:.1f} s not included)")
        print(f"  peak wall displacement  {1e3 * peak['max_displacement_m']:.3f} mm")
        print(f"  peak strain energy      {1e6 * peak['strain_energy_J']:.3f} uJ")
        print(f"  peak Green strain       {peak['max_strain']:.4f}")
        print(f"  non-linear elements     {100 * peak['nonlinear_fraction']:.1f} % at most")
        print(f"  CG iterations per step  {peak['solver_iterations']} at most")
        print(f"  warnings                {len(messages)}")
        print(f"results: {csv_path} and {out / 'summary.json'}")
    return 0
