"""The summary of a run: the dict written as ``summary.json`` and the text printed after a run."""
from __future__ import annotations

from orchestration.errors import short_status_name


def fmu_messages(messages: list[tuple[str, int, str]]) -> list[dict]:
    """Log messages at warning level and above, as summary entries."""
    return [{"component": comp, "status": short_status_name(status), "message": text}
            for comp, status, text in messages if status >= 1]


def format_summary(summary: dict, units: dict[str, str]) -> str:
    """The readable summary: ``units`` maps "component.port" to its unit."""
    def unit(ref: str) -> str:
        u = units.get(ref)
        return f" {u}" if u else ""

    lines = []
    rtf = summary["real_time_factor"]
    head = (f"{summary['scene']}: {summary['status']}, {summary['simulated_time_s']:.4g} s simulated in "
            f"{summary['wall_time_s']:.3g} s")
    if rtf:
        head += f" (real-time factor {rtf:.2f}, {summary['hosting']}; setup {summary['setup_time_s']:.1f} s)"
    lines.append(head)
    if summary["error"]:
        lines.append(f"  {'reason' if summary['status'] == 'terminated' else 'error'}: {summary['error']}")
    warnings = summary.get("warnings", [])  # outputs beyond their plausible range: results to distrust
    for warning in warnings[:5]:
        lines.append(f"  WARNING: {warning}")
    if len(warnings) > 5:
        lines.append(f"  WARNING: and {len(warnings) - 5} more (summary.json lists them)")
    for name, comp in summary["components"].items():
        line = f"  {name:10s} {comp['rate_hz']:8.6g} Hz  {comp['steps']:7d} steps  busy {comp['busy_wall_s']:6.2f} s"
        cost = comp.get("step_cost")
        # every step counts: the worst, and the steps longer than their period in real time
        if cost:
            line += (f"  step median {1e3 * cost['median_s']:.3g}, p99 {1e3 * cost['p99_s']:.3g}, max "
                     f"{1e3 * cost['max_s']:.3g} ms; {cost['over_budget']} over {1e3 * cost['budget_s']:.3g} ms")
        lines.append(line)
    for ref, peak in summary.get("peaks", {}).items():
        lines.append(f"  peak {ref:32s} {peak['value']:.4g}{unit(ref)} at {peak['time_s']:.3f} s")
    for ref, e in summary.get("energy", {}).items():
        u = unit(ref)
        lines.append(f"  energy {ref:30s} final {e['final']:.4g}{u}, range [{e['min']:.4g}, {e['max']:.4g}]{u}, "
                     f"drift {e['drift']:.4g}{u}")
    for ref, w in summary.get("operator_warnings", {}).items():
        first = f", first at {w['first_s']:.3f} s" if w["first_s"] is not None else ""
        lines.append(f"  warning {ref:29s} raised {w['count']} time(s), on for {w['time_on_s']:.3f} s{first}")
    if "deadlines" in summary:
        d = summary["deadlines"]
        line = f"  haptic deadlines missed: {d['missed']} of {d['haptic_steps']}"
        if "lateness_p50_s" in d:
            line += (f"; lateness p50 {1e3 * d['lateness_p50_s']:.3f} ms, p99 {1e3 * d['lateness_p99_s']:.3f} ms, "
                     f"max {1e3 * d['lateness_max_s']:.3f} ms")
        lines.append(line)
        if d.get("cpus"):
            lines.append("  CPUs: " + ", ".join(f"{name} on {cpu}" for name, cpu in d["cpus"].items()))
    messages = summary.get("fmu_messages", [])
    errors = [m for m in messages if m["status"] in ("error", "fatal")]
    lines.append(f"  FMU messages: {len(messages)} ({len(errors)} errors)" if messages else "  FMU messages: none")
    for m in messages[:5]:
        lines.append(f"    {m['component']} [{m['status']}] {m['message'][:200]}")
    lines.append(f"  results in {summary['results']['folder']}/: summary.json, a CSV per component, "
                 "PNG plots, surfaces as .pvd (ParaView)")
    lost = summary.get("lost", [])
    for loss in lost[:5]:
        lines.append(f"  LOST: {loss}")
    if len(lost) > 5:
        lines.append(f"  LOST: and {len(lost) - 5} more (summary.json lists them)")
    for error in summary["results"].get("surface_errors", [])[:5]:
        lines.append(f"  surface frame not written: {error}")
    for error in summary["results"].get("row_errors", [])[:5]:
        lines.append(f"  CSV rows: {error}")
    return "\n".join(lines)
