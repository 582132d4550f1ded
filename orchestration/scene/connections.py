"""Connections between components: endpoints, causality, types, sizes, units, rates and transitions,
and algebraic loops."""
from __future__ import annotations

from orchestration.hosts.description import READABLE, WRITABLE, PortInfo, conversion_problem
from orchestration.plan import transitions as tr
from orchestration.scene.model import DEFAULT_ORDERING, ComponentSpec, ConnectionSpec, ORDERINGS, Ordering
from orchestration.scene.tables import unknown_keys
from orchestration.scene.values import type_of


_CONNECTION_KEYS = {"from", "to", "transition", "ordering"}


def parse_endpoint(text, where: str, problems: list[str]) -> tuple[str, str] | None:
    if not isinstance(text, str) or text.count(".") != 1 or not all(text.split(".")):
        problems.append(f"{where}: {text!r} is not \"component.port\" (e.g. \"contact.tool_force\")")
        return None
    comp, port = text.split(".")
    return comp.strip(), port.strip()


def load_connections(items, components: dict[str, ComponentSpec], problems: list[str],
                      declared: set[str] = frozenset()) -> list[ConnectionSpec]:
    """Connections; one to a component that is declared but could not be loaded (its problem is
    reported already) is skipped silently rather than reported again as unknown."""
    if not isinstance(items, list):
        problems.append("connection: write each connection as a [[connection]] table")
        return []
    connections: list[ConnectionSpec] = []
    targets: dict[tuple[str, str], str] = {}
    for index, item in enumerate(items, start=1):
        where = f"connection {index}"
        if not isinstance(item, dict):
            problems.append(f"{where}: must be a table with from and to")
            continue
        unknown_keys(item, _CONNECTION_KEYS, where, problems)
        src = parse_endpoint(item.get("from"), f"{where} from", problems)
        dst = parse_endpoint(item.get("to"), f"{where} to", problems)
        if src is None or dst is None:
            continue
        where = f"connection {index} ({item['from']} -> {item['to']})"
        ok = _endpoints_exist(where, src, dst, components, declared, problems)
        transition = item.get("transition")
        if transition is not None and transition not in tr.REGISTRY:
            problems.append(f"{where} transition: {transition!r} is not one of {', '.join(tr.REGISTRY)}")
            ok = False
        ordering = item.get("ordering", DEFAULT_ORDERING)
        if ordering not in ORDERINGS:
            problems.append(f"{where} ordering: {ordering!r} is not one of {', '.join(ORDERINGS)}")
            ok = False
        if not ok:
            continue
        _check_ports_match(where, src, dst, components, problems)
        key = (dst[0], dst[1])
        if key in targets:
            problems.append(f"{where}: {dst[0]}.{dst[1]} is already driven by {targets[key]}; an input has one source")
        targets[key] = where
        _check_rates(where, components[src[0]], components[dst[0]], components[dst[0]].ports[dst[1]], transition,
                     problems)
        if src[0] == dst[0]:
            problems.append(f"{where}: connects a component to itself")
        connections.append(ConnectionSpec(src[0], src[1], dst[0], dst[1], transition, ordering, index))
    return connections


def _endpoints_exist(where: str, src, dst, components: dict, declared: set, problems: list[str]) -> bool:
    """Whether both ends are ports of loaded components with the causality a connection needs."""
    ok = True
    for (comp, port), role, allowed in ((src, "from", READABLE), (dst, "to", WRITABLE)):
        spec = components.get(comp)
        if spec is None:
            if comp not in declared:
                problems.append(f"{where}: unknown component {comp!r}; components: "
                                f"{', '.join(components) or 'none'}")
            ok = False
            continue
        info = spec.ports.get(port)
        if info is None:
            names = sorted(n for n, p in spec.ports.items() if p.causality in allowed)
            problems.append(f"{where}: {comp} has no port {port!r}; "
                            f"{'outputs' if role == 'from' else 'inputs'}: {', '.join(names)}")
            ok = False
        elif info.causality not in allowed:
            article = "an" if info.causality[0] in "aeiou" else "a"
            problems.append(f"{where}: {comp}.{port} is {article} {info.causality}; a connection goes "
                            f"{'from an output' if role == 'from' else 'to an input or parameter'}")
            ok = False
    return ok


def _check_ports_match(where: str, src, dst, components: dict, problems: list[str]) -> None:
    """The two ends' types, sizes and units."""
    out_spec, in_spec = components[src[0]], components[dst[0]]
    out_port, in_port = out_spec.ports[src[1]], in_spec.ports[dst[1]]
    conversion = conversion_problem(out_port, in_port)
    if conversion:
        problems.append(f"{where}: type mismatch, {src[0]}.{src[1]} is {type_of(out_port)} and {dst[0]}.{dst[1]} "
                        f"is {type_of(in_port)}: {conversion}")
    if out_port.size != in_port.size:
        hint = _size_hint(in_spec, in_port, out_port)
        problems.append(f"{where}: size mismatch, {out_port.size} values "
                        f"({'x'.join(map(str, out_port.shape)) or 'scalar'}) -> {in_port.size} "
                        f"({'x'.join(map(str, in_port.shape)) or 'scalar'}){hint}")
    if out_port.unit and in_port.unit and out_port.unit != in_port.unit:
        problems.append(f"{where}: unit mismatch, {out_port.unit} -> {in_port.unit} ({src[0]}.{src[1]} is in "
                        f"{out_port.unit}, {dst[0]}.{dst[1]} in {in_port.unit}); the master converts no units")


def _check_rates(where: str, out_spec: ComponentSpec, in_spec: ComponentSpec, in_port, transition: str | None,
                 problems: list[str]) -> None:
    """A connection between rates names its transition, and the transition can join them."""
    is_parameter = in_port.causality != "input"
    rates_known = not (out_spec.is_fmu and out_spec.step is None) and not (in_spec.is_fmu and in_spec.step is None)
    rates_differ = (rates_known and not out_spec.is_continuous and not is_parameter and out_spec.step != in_spec.step)
    if rates_differ and transition is None:
        choices = " | ".join(f'"{name}"' for name in tr.REGISTRY)
        problems.append(f"{where}: connects a {_rate(out_spec)} output to a {_rate(in_spec)} input; name the rate "
                        f"transition: transition = {choices}")
    if transition is not None and not out_spec.is_continuous:
        problem = tr.REGISTRY[transition].scene_problem(out_spec.step, in_spec.step)
        if problem:
            problems.append(f"{where} transition: {problem}")


def _rate(spec: ComponentSpec) -> str:
    if spec.step is None:
        return "continuous"
    hz = 1 / spec.step
    return f"{float(hz):g} Hz"


def _size_hint(spec: ComponentSpec, in_port: PortInfo, out_port: PortInfo) -> str:
    if not spec.is_fmu or not spec.description:
        return ""
    md = spec.description.model_description
    for v in md.modelVariables:
        if v.name == in_port.name and v.dimensions:
            refs = [d.valueReference for d in v.dimensions if d.valueReference is not None]
            names = [w.name for w in md.modelVariables if w.valueReference in refs]
            if names and len(out_port.shape) == len(in_port.shape):
                fix = ", ".join(f"{n} = {out_port.shape[i]}" for i, n in enumerate(names) if i < len(out_port.shape))
                return f"; set {spec.name} parameter {fix}"
    return ""


def check_algebraic_loops(connections: list[ConnectionSpec], components: dict, problems: list[str]) -> None:
    """A cycle of Gauss-Seidel connections has no order to step in: one of them must be Jacobi."""
    graph: dict[str, set[str]] = {}
    for c in connections:
        if c.ordering == Ordering.GAUSS_SEIDEL and c.source in components and c.target in components \
                and not components[c.source].is_continuous \
                and components[c.target].ports.get(c.target_port, PortInfo("", "input", "")).causality == "input":
            graph.setdefault(c.source, set()).add(c.target)
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        state[node] = 2
        stack.pop()
        return None

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            if cycle:
                problems.append(f"algebraic loop of gauss-seidel connections {' -> '.join(cycle)}: set "
                                "ordering = \"jacobi\" on one of them (that input then uses the value from before the step)")
                return
