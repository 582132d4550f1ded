"""Shared fixtures: the real FMUs, built once per test session from this checkout."""
from __future__ import annotations

from pathlib import Path

import pytest

from orchestration.build import build_fmu

REPO = Path(__file__).resolve().parent.parent
CCD_DATA = REPO.parent / "shared" / "data" / "ccd-sample-queries"


@pytest.fixture(scope="session")
def fmu_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fmus")


@pytest.fixture(scope="session")
def tissue_fmu(fmu_dir) -> Path:
    return build_fmu("Tissue", fmu_dir)


@pytest.fixture(scope="session")
def catheter_fmu(fmu_dir) -> Path:
    return build_fmu("Catheter", fmu_dir)


@pytest.fixture(scope="session")
def contact_fmu(fmu_dir) -> Path:
    return build_fmu("Contact", fmu_dir)
