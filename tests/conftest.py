"""Shared fixtures: the real FMUs, built once per test session from this checkout."""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

from fmu_build.package import build_fmu
from project import FMU_NAMES, fmu_file_name

# Fuzzers (tests/test_fuzz_*.py) run a bounded number of cases in CI and many more on demand:
#     pytest tests/test_fuzz_*.py --hypothesis-profile=long
# Each fuzz case is a fresh process or a whole run, hence no deadline and few cases in CI.
settings.register_profile("ci", max_examples=25, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
settings.register_profile("long", max_examples=1000, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
# Any other number of cases per fuzz test: AAA_FUZZ_EXAMPLES=200 pytest tests/test_fuzz_*.py
if os.environ.get("AAA_FUZZ_EXAMPLES"):
    settings.register_profile("fuzz-examples", settings.get_profile("long"),
                              max_examples=int(os.environ["AAA_FUZZ_EXAMPLES"]))
    settings.load_profile("fuzz-examples")
else:
    settings.load_profile("ci")

REPO = Path(__file__).resolve().parent.parent
CCD_DATA = REPO.parent / "shared" / "data" / "ccd-sample-queries"


@pytest.fixture(scope="session", autouse=True)
def temporary_files_in_the_session_folder(tmp_path_factory):
    """Every temporary file of the tests and of the processes they start in a folder of the session,
    removed at its end: an importer's extraction of a 150 MB FMU that a failing call leaves behind
    (FMPy's ``simulate_fmu`` cleans up only when it returns) never piles up in /tmp run after run."""
    folder = tmp_path_factory.mktemp("tmp")
    saved = os.environ.get("TMPDIR"), tempfile.tempdir
    os.environ["TMPDIR"] = tempfile.tempdir = str(folder)
    yield folder
    if saved[0] is None:
        os.environ.pop("TMPDIR", None)
    else:
        os.environ["TMPDIR"] = saved[0]
    tempfile.tempdir = saved[1]
    shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope="session")
def fmu_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fmus")


@pytest.fixture(scope="session")
def built_fmu(fmu_dir):
    """``built_fmu(name)`` -> path of the .fmu: an FMU of the build's table (tests/project.py) built
    from this checkout into ``fmu_dir``, once per session and only when a test asks for it."""
    built: dict[str, Path] = {}

    def build(name: str) -> Path:
        if name not in built:
            built[name] = build_fmu(name, fmu_dir)
        return built[name]

    return build


@pytest.fixture(scope="session")
def fmus(built_fmu) -> dict[str, Path]:
    """Every FMU of the build's table: name -> path of the .fmu."""
    return {name: built_fmu(name) for name in FMU_NAMES}


def _fmu_fixture(name: str):
    def fixture(built_fmu) -> Path:
        return built_fmu(name)

    fixture.__doc__ = f"{name}.fmu, built once per session (the build's table names it)."
    return pytest.fixture(scope="session", name=f"{name.lower()}_fmu")(fixture)


# One fixture per FMU of the table, named after it: tissue_fmu, contact_fmu, catheter_fmu, ...
for _name in FMU_NAMES:
    globals()[f"{_name.lower()}_fmu"] = _fmu_fixture(_name)
del _name


@pytest.fixture(scope="session")
def fmus_in_repo() -> dict[str, Path]:
    """The FMUs of the table built into fmus/, where the shipped scenes and the command line find
    them (when missing or older than their sources; the numba cache warmed), as ``python -m
    orchestration run`` does first: name -> path of the .fmu. For every test that loads a shipped
    scene or runs the command line, so that it passes alone on a fresh clone."""
    from fmu_build.paths import DEFAULT_FMU_DIR
    from orchestration.app.warmup import ensure_fmus_built

    ensure_fmus_built(quiet=True)
    return {name: DEFAULT_FMU_DIR / fmu_file_name(name) for name in FMU_NAMES}


@pytest.fixture(params=["importer", "helper"])
def model_process(request, monkeypatch) -> str:
    """Where the FMUs' models run (src/fmi3_layer/remote.h): in the importer's process, or in the
    helper process the FMU starts; set for this process and the processes a test starts."""
    monkeypatch.setenv("AAA_COSIM_MODEL_PROCESS", request.param)
    return request.param


@pytest.fixture(scope="session")
def c_host(tmp_path_factory) -> Path:
    """The non-Python importer tests/c_host/fmu_host.c, compiled once with the system C compiler."""
    from fuzz_hosts import compile_c_host

    return compile_c_host(tmp_path_factory.mktemp("c_host"))


# -- synthetic FMUs for the orchestrator's host tests (tests/synthetic/synthetic_fmu) ------------
from fmu_build.specs import FmuSpec
from fmu_build.package import build_fmu_from_spec  # noqa: E402

SYNTHETIC_ROOT = Path(__file__).resolve().parent / "synthetic"


SYNTHETIC_SPECS = {
    name: FmuSpec(name, "synthetic_fmu", f"fmu:{name.upper()}", source_root=SYNTHETIC_ROOT)
    for name in ("Signal", "Echo", "Faulty")
}


@pytest.fixture(scope="session")
def synthetic_fmus(tmp_path_factory) -> dict[str, Path]:
    """Signal, Echo and Faulty built once per session: name -> path of the .fmu."""
    dest = tmp_path_factory.mktemp("synthetic_fmus")
    return {name: build_fmu_from_spec(spec, dest) for name, spec in SYNTHETIC_SPECS.items()}
