"""The sizes two FMUs must agree on (src/fmi3_layer/coupling.py) start equal in the built FMUs,
so the three connect as they are, and a scene that sets one size differently is told which other."""

from __future__ import annotations

from orchestration.hosts.description import read_fmu


def test_the_fmus_start_with_the_sizes_they_share(fmus):
    tissue, contact, catheter = (read_fmu(fmus[name]).ports for name in ("Tissue", "Contact", "Catheter"))
    assert contact["n_tool_points"].start == catheter["n_tool_points"].start == 31
    assert contact["max_patch_nodes"].start == tissue["n_patch_nodes"].start == 16
    # and the arrays they size agree as declared
    assert contact["tool_positions"].size == catheter["centerline_positions"].size == 31 * 3
    assert contact["patch_nodes"].size == tissue["patch_nodes"].size == 16
