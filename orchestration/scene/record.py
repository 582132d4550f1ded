"""What a run records: the streams, surfaces and plots of ``[record]``, their file names inside the
result folder."""
from __future__ import annotations

import re

from orchestration.hosts.description import INTEGER_RANGES, NUMERIC_TYPES
from orchestration.scene.model import SurfaceSpec
from orchestration.scene.tables import expect_list, expect_strings, expect_tables, short_text, unknown_keys
from orchestration.scene.text import FILE_NAME


_SURFACE_KEYS = {"component", "positions", "triangles", "every", "point_data", "name"}
_PLOT_KEYS = {"file", "title", "panels"}
_PANEL_KEYS = {"ylabel", "series"}
_SERIES_KEYS = {"stream", "column", "label", "norm"}


def load_record(table: dict, components: dict, problems: list[str], declared=frozenset()):
    """What to record; a component that is declared but could not be loaded (its problem is
    reported already) is skipped rather than reported again as unknown."""
    record: dict[str, list[str]] = {}
    surfaces: list[SurfaceSpec] = []
    plots: list[dict] = []
    for key, value in table.items():
        if key == "surfaces":
            items = expect_list(value, "[record] surfaces", problems, "write each as a [[record.surfaces]] table")
            for i, item in enumerate(items):
                surface = _load_surface(f"[record] surfaces[{i}]", item, components, problems, declared)
                if surface is None:
                    continue
                # <name>.pvd and the folder <name>/ beside <component>.csv and units.json
                taken = {s.name for s in surfaces} | {k for k in table if k not in ("surfaces", "plots")} | {"units"}
                if surface.name in taken:
                    problems.append(f"[record] surfaces[{i}] name: {surface.name!r} is already the name of another "
                                    "recorded file (a surface, a component's CSV or units); give another name")
                else:
                    surfaces.append(surface)
        elif key == "plots":
            items = expect_list(value, "[record] plots", problems, "write each figure as a [[record.plots]] table")
            plots = [item for i, item in enumerate(items) if _plot_ok(i, item, components, problems, declared)]
        else:
            comp = components.get(key)
            if comp is None:
                if key not in declared:
                    problems.append(f"[record] {key}: unknown component; components: {', '.join(components)}")
                continue
            if not isinstance(value, list):
                problems.append(f"[record] {key}: must be a list of port names (got {short_text(value)})")
                continue
            ports = expect_strings(value, f"[record] {key}", problems, "a port name")
            seen: set[str] = set()
            for port in ports:
                info = comp.ports.get(port)
                if port in seen:
                    # The CSV would have two columns of one name and the run would refuse it.
                    problems.append(f"[record] {key}: {port!r} is listed twice; list each port once")
                seen.add(port)
                if info is None:
                    problems.append(f"[record] {key}: no port {port!r}")
                elif info.type not in NUMERIC_TYPES:
                    problems.append(f"[record] {key}.{port}: a {info.type} variable cannot be recorded; the CSV records "
                                    "numbers, Booleans and enumerations (their values)")
                elif info.size > 64:
                    problems.append(f"[record] {key}.{port}: {info.size} values is too many for a CSV column set; "
                                    "record surfaces with [[record.surfaces]]")
            if comp.is_continuous and not comp.is_fmu:  # an FMU without a step has its own problem
                problems.append(f"[record] {key}: a continuous source has no steps to record at; record the input it drives")
                continue
            record[key] = list(dict.fromkeys(ports))
    _check_result_names(table, record, surfaces, plots, problems)
    _check_plot_columns(table, record, plots, components, problems)
    return record, surfaces, plots


#: files every run writes in its result folder, whatever the scene (recording, summary)
_FIXED_RESULTS = {"summary.json": "the run's summary", "units.json": "the units of the CSV columns"}
#: labels of the summary's "results" table (summary.json) that are not a stream or a surface
_SUMMARY_LABELS = ("folder", "units", "plots", "surface_errors", "row_errors")


def _check_result_names(table: dict, record: dict, surfaces: list, plots: list, problems: list[str]) -> None:
    """Every file and folder a run writes into its result folder has one writer: the fixed files,
    ``<component>.csv``, each figure, and each surface's ``<name>.pvd`` and frame folder ``<name>/``.
    Two writers of one name lose a result or end the run with an error, so validate refuses them
    (compared without case: many file systems do not tell ``Forces.png`` from ``forces.png``)."""
    claimed: dict[str, tuple[str, str]] = {name.casefold(): (name, f"{name}, {role}")
                                          for name, role in _FIXED_RESULTS.items()}

    def claim(name: str, owner: str, where: str, what: str, fix: str) -> None:
        key = name.casefold()
        if key not in claimed:
            claimed[key] = (name, owner)
            return
        first, holder = claimed[key]
        case = " (the names differ only in case, which many file systems do not tell apart)" if first != name else ""
        problems.append(f"{where}: {what} {name} in the result folder, which is already {holder}{case}; {fix}")

    for component in record:
        claim(f"{component}.csv", f"the CSV of [record] {component}", f"[record] {component}", "writes",
              "rename one of the components")
        if component in _SUMMARY_LABELS:
            problems.append(f"[record] {component}: {component!r} is a name summary.json's results use for "
                            "something else; rename the component to record it")
    raw_plots = table.get("plots") if isinstance(table.get("plots"), list) else []
    for figure in plots:
        i = next((k for k, item in enumerate(raw_plots) if item is figure), "?")
        claim(figure["file"], f"the figure of [record] plots[{i}]", f"[record] plots[{i}] file",
              f"{figure['file']!r} would write", "give each figure a file of its own")
    raw_surfaces = table.get("surfaces") if isinstance(table.get("surfaces"), list) else []
    for surface in surfaces:
        i = next((k for k, item in enumerate(raw_surfaces) if isinstance(item, dict)
                  and item.get("name", f"{item.get('component')}_surface") == surface.name), "?")
        where, fix = f"[record] surfaces[{i}] name", "give the surface another name"
        claim(f"{surface.name}.pvd", f"the ParaView collection of [record] surfaces[{i}]", where,
              f"{surface.name!r} would write", fix)
        claim(surface.name, f"the frame folder of [record] surfaces[{i}]", where,
              f"{surface.name!r} would write its frame folder", fix)
        if surface.name in _SUMMARY_LABELS and surface.name != "units":  # "units": reported by load_record
            problems.append(f"{where}: {surface.name!r} is a name summary.json's results use for something else; "
                            "give the surface another name")


#: a column of an array port as the CSV header writes it: "tool_force[2]"
_ELEMENT = re.compile(r"(?P<port>.+)\[(?P<index>0|[1-9][0-9]*)\]")


def _check_plot_columns(table: dict, record: dict, plots: list, components: dict, problems: list[str]) -> None:
    """A figure's series reads its column from the stream's CSV: a column the scene does not record
    would only draw an empty panel at the end of the run, so validate refuses it. A stream whose
    [record] entry has a problem of its own (reported already) or whose component did not load is
    not checked again."""
    raw_plots = table.get("plots") if isinstance(table.get("plots"), list) else []
    for figure in plots:
        i = next((k for k, item in enumerate(raw_plots) if item is figure), "?")
        for j, panel in enumerate(figure.get("panels", [])):
            for k, series in enumerate(panel.get("series", [])):
                at = f"[record] plots[{i}] panels[{j}] series[{k}]"
                stream, column = series["stream"], series["column"]
                if stream not in components or (stream in table and stream not in record):
                    continue
                if stream not in record:
                    problems.append(f"{at} stream: {stream} is not recorded, so there is no {stream}.csv to plot: add "
                                    f"{stream} = [\"{column}\"] to [record]")
                    continue
                ports = record[stream]
                element = _ELEMENT.fullmatch(column)
                if column in ports:
                    continue
                if element and element["port"] in ports:
                    info = components[stream].ports.get(element["port"])
                    if info is None or 1 < info.size and int(element["index"]) < info.size:
                        continue
                    if info.size == 1:
                        problems.append(f"{at} column: {stream}.{element['port']} is a single value, its column is "
                                        f"{element['port']!r} (not {column!r})")
                    else:
                        problems.append(f"{at} column: {column!r} is beyond {stream}.{element['port']}, which has "
                                        f"{info.size} values ([0] to [{info.size - 1}])")
                    continue
                problems.append(f"{at} column: {stream} records no column {column!r} (it records "
                                f"{', '.join(ports) or 'nothing'}); add {column!r} to [record] {stream} or plot one "
                                "of those")


def _load_surface(where: str, item, components: dict, problems: list[str], declared) -> SurfaceSpec | None:
    if not isinstance(item, dict):
        problems.append(f"{where}: must be a table {{ component, positions, triangles }}")
        return None
    unknown_keys(item, _SURFACE_KEYS, where, problems)
    component = item.get("component")
    comp = components.get(component) if isinstance(component, str) else None
    if comp is None:
        if not isinstance(component, str) or component not in declared:
            problems.append(f"{where}: unknown component {short_text(component)}; components: {', '.join(components)}")
        return None
    ok = True
    for role in ("positions", "triangles"):
        if not isinstance(item.get(role), str) or item.get(role) not in comp.ports:
            problems.append(f"{where} {role}: {comp.name} has no port {short_text(item.get(role))}")
            ok = False
            continue
        # what the recording needs (recording.write_surface): flat (n, 3) numbers, triangles in integers
        port = comp.ports[item[role]]
        integer = port.type in INTEGER_RANGES and port.type != "Enumeration"
        if port.type not in NUMERIC_TYPES or port.type == "Boolean" or port.size % 3 or port.size == 0 or (
                role == "triangles" and not integer):
            kind = "integer node ids, 3 per triangle" if role == "triangles" else "numbers, 3 per node (x, y, z)"
            problems.append(f"{where} {role}: {comp.name}.{port.name} is {port.describe()}; {role} are {kind}")
            ok = False
    nodes = comp.ports[item["positions"]].size // 3 if ok else None
    point_data = expect_strings(expect_list(item.get("point_data", []), f"{where} point_data", problems, "of port names"),
                          f"{where} point_data", problems, "a port name")
    for extra in point_data:
        if extra not in comp.ports:
            problems.append(f"{where} point_data: {comp.name} has no port {extra!r}")
            ok = False
        elif nodes is not None and comp.ports[extra].size not in (nodes, 3 * nodes):
            problems.append(f"{where} point_data: {comp.name}.{extra} holds {comp.ports[extra].size} values; point "
                            f"data has one or three per node ({nodes} or {3 * nodes})")
            ok = False
    if comp.is_continuous and not comp.is_fmu:
        problems.append(f"{where}: {comp.name} is a continuous source, it has no steps to record frames at; "
                        "record the surface of a stepped component")
        ok = False
    every = item.get("every", 1)
    if not isinstance(every, int) or isinstance(every, bool) or every < 1:
        problems.append(f"{where} every: must be a positive integer, a frame every so many steps (got {short_text(every)})")
        ok = False
    name = item.get("name", comp.name + "_surface")
    if not isinstance(name, str) or not FILE_NAME.fullmatch(name):
        problems.append(f"{where} name: {short_text(name)} is not a plain name: it names <name>.pvd in the result "
                        "folder, so it is letters, digits, '_', '-' or '.', not starting with '.' (no '/')")
        ok = False
    if not ok:
        return None
    return SurfaceSpec(comp.name, item["positions"], item["triangles"], every, tuple(point_data), name)


def _plot_ok(index: int, figure, components: dict, problems: list[str], declared) -> bool:
    """Check one [[record.plots]] figure as plots.plot_signals will draw it at the end of the run."""
    where = f"[record] plots[{index}]"
    if not isinstance(figure, dict):
        problems.append(f"{where}: must be a table {{ file, title, panels }}")
        return False
    count = len(problems)
    unknown_keys(figure, _PLOT_KEYS, where, problems)
    file = figure.get("file")
    if not isinstance(file, str) or not FILE_NAME.fullmatch(file) or not file.lower().endswith(".png"):
        problems.append(f"{where} file: {short_text(file)} is not a plain .png file name in the result folder "
                        "(e.g. \"forces.png\"; no '/')")
    if not isinstance(figure.get("title", ""), str):
        problems.append(f"{where} title: must be a string")
    panels = figure.get("panels")
    if not isinstance(panels, list) or not panels:
        problems.append(f"{where} panels: must be a non-empty list of {{ ylabel, series = [...] }}")
        panels = []
    for at, panel in expect_tables(panels, f"{where} panels", _PANEL_KEYS, problems, "{ ylabel, series = [...] }"):
        if not isinstance(panel.get("ylabel", ""), str):
            problems.append(f"{at} ylabel: must be a string")
        series_list = expect_list(panel.get("series", []), f"{at} series", problems, "of { stream, column, label }")
        for at_series, series in expect_tables(series_list, f"{at} series", _SERIES_KEYS, problems,
                                             "{ stream, column, label }"):
            stream, column = series.get("stream"), series.get("column")
            if not isinstance(stream, str) or (stream not in components and stream not in declared):
                problems.append(f"{at_series} stream: {short_text(stream)} is not a component of the scene")
            if not isinstance(column, str) or not column:
                problems.append(f"{at_series} column: must be a port name (got {short_text(column)})")
            if not isinstance(series.get("label", ""), str):
                problems.append(f"{at_series} label: must be a string")
            if not isinstance(series.get("norm", False), bool):
                problems.append(f"{at_series} norm: must be true or false")
    return len(problems) == count
