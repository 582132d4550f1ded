"""Before a run: the FMUs built and their kernels compiled, so that a run compiles nothing while it is timed.

The carried kernels (``fmu_build.kernels``) and this machine's numba cache are both compiled by a
run of the default scene, which is why this lives with the orchestrator, not with the build.
"""
from __future__ import annotations

import datetime
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

from fmu_build.errors import BuildError
from fmu_build.kernels import (CARRIED_KERNELS, carried_kernel_folders, fmu_set_digest, numba_cache_damage,
                               usable_cache_root, write_carried_kernels)
from fmu_build.package import build_fmu, fmu_is_stale, has_entries
from fmu_build.paths import DEFAULT_FMU_DIR, REPO_ROOT, SCENE_DIR
from fmu_build.portable_runtime import prepare_carried_runtime
from fmu_build.specs import FMU_SPECS, available_fmus
from orchestration.run.compiled_loop import compiled_loop_library
from orchestration.run.status import RunStatus
from orchestration.scene.model import Hosting

logger = logging.getLogger(__name__)


def add_carried_kernels(fmus: list[Path], quiet: bool = False) -> None:
    """Put into each of the project's FMUs that carries a runtime the kernels compiled for any
    x86-64 CPU (resources/numba_cache): a first load on another machine then loads them instead
    of compiling (Contact: ~30 s). They are compiled by running the default scene once with those
    FMUs, once per version of the sources (the cache is content-addressed, build/numba-carried);
    an FMU built after that has them already (``fmu_build.kernels.write_carried_kernels``)."""
    finish_carried_kernels(start_carried_kernels(fmus, quiet))


@dataclass
class _CarriedKernelJob:
    fmus: list[Path]
    compiling: subprocess.Popen | None  # the default scene run that compiles them, when needed


def start_carried_kernels(fmus: list[Path], quiet: bool = False) -> _CarriedKernelJob | None:
    """add_carried_kernels in two halves, so that other work can run while the kernels compile:
    this starts the compiling run (when needed); finish_carried_kernels waits and adds them."""
    specs = {spec.model_identifier: spec for spec in FMU_SPECS.values()}
    fmus = [f for f in fmus if f.stem in specs and has_entries(f, "resources/runtime.id")
            and not has_entries(f, "resources/numba_cache/")]
    if not fmus:
        return None
    compiling = None
    if any(not carried_kernel_folders(specs[f.stem], CARRIED_KERNELS) for f in fmus):
        if not quiet:
            print("compiling the kernels the FMUs carry (once per source version) ...", flush=True)
        code = "import sys; from orchestration.app.warmup import warm_run; sys.exit(warm_run(sys.argv[1]))"
        env = {**os.environ, "NUMBA_CPU_NAME": "generic", "AAA_COSIM_NUMBA_CACHE": str(CARRIED_KERNELS)}
        env.pop("NUMBA_CPU_FEATURES", None)
        compiling = subprocess.Popen([sys.executable, "-c", code, str(fmus[0].parent)], cwd=str(REPO_ROOT), env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return _CarriedKernelJob(fmus, compiling)


def finish_carried_kernels(job: _CarriedKernelJob | None) -> None:
    """The second half of add_carried_kernels (see start_carried_kernels)."""
    if job is None:
        return
    if job.compiling is not None:
        out, err = job.compiling.communicate()
        if job.compiling.returncode != 0:
            logger.warning("compiling the kernels the FMUs carry failed (their first load elsewhere compiles them): %s",
                           (err or out).strip()[-2000:])
            return
    specs = {spec.model_identifier: spec for spec in FMU_SPECS.values()}
    for fmu in job.fmus:
        partial = fmu.with_name(f".{fmu.name}.kernels.partial")
        shutil.copyfile(fmu, partial)
        with zipfile.ZipFile(partial, "a", zipfile.ZIP_DEFLATED) as archive:
            added = write_carried_kernels(archive, specs[fmu.stem])
        if added:
            partial.replace(fmu)
        else:
            partial.unlink()


def ensure_fmus_built(quiet: bool = False) -> None:
    """Build the project's FMUs into fmus/ when missing or older than their sources, then warm the
    numba cache their kernels compile into, so that a run compiles nothing while it is timed."""
    if any(fmu_is_stale(name) for name in available_fmus()):
        prepare_carried_runtime(quiet)
    for name in available_fmus():
        if fmu_is_stale(name):
            if not quiet:
                print(f"building fmus/{name}.fmu ...", flush=True)
            try:
                build_fmu(name)
            except BuildError as exc:
                raise BuildError(f"fmus/{name}.fmu is missing or older than its sources and cannot be built: "
                                 f"{exc}") from None
    # the kernels the FMUs carry compile in another process while this CPU's are warmed (2 cores)
    carried = start_carried_kernels(sorted(DEFAULT_FMU_DIR.glob("*.fmu")), quiet=quiet)
    try:
        try:  # the master's compiled loop, so that the first run does not compile it while it is timed
            compiled_loop_library()
        except BuildError as exc:
            logger.warning("%s; runs make every step from Python", exc)
        warm_numba_cache(quiet)
    finally:
        finish_carried_kernels(carried)


def warm_numba_cache(quiet: bool = False, dest: Path = DEFAULT_FMU_DIR) -> bool:
    """Compile the FMUs' kernels into the numba cache by running the default scene once.

    The FMUs import their packages under names of their own and cache compiled kernels by file
    content (``numba_cache``), so a run in a fresh interpreter compiles exactly what later runs
    load. Done once per set of FMUs (a stamp in the cache folder); returns True if it ran.
    """
    fmus = sorted(Path(dest).glob("*.fmu"))
    if not fmus:
        return False
    root = usable_cache_root()
    if root is None:
        return False
    damage = numba_cache_damage(root)
    if damage:
        raise BuildError(damage)
    try:
        digest = fmu_set_digest(fmus)
    except OSError as exc:
        raise BuildError(f"cannot read the FMU {exc.filename} ({exc.strerror or exc}): rebuild the FMUs with "
                         "`python -m orchestration build`, as a user who may write and read them") from None
    except zipfile.BadZipFile as exc:
        raise BuildError(f"an FMU in {dest} is not a complete archive ({exc}): rebuild the FMUs with "
                         "`python -m orchestration build`") from None
    stamp = root / f"warmed-{digest}"
    if stamp.exists():
        return False
    if not quiet:
        print("compiling the FMUs' numba kernels (once per build) ...", flush=True)
    code = "import sys; from orchestration.app.warmup import warm_run; sys.exit(warm_run())"
    result = subprocess.run([sys.executable, "-c", code], cwd=str(REPO_ROOT), capture_output=True, text=True)
    if result.returncode != 0:  # a warm-up failure only costs time later: say so, do not stop
        logger.warning("warming the numba cache failed (runs will compile their kernels): %s",
                       (result.stderr or result.stdout).strip()[-2000:])
        return False
    try:
        root.mkdir(parents=True, exist_ok=True)
        stamp.write_text(datetime.datetime.now().isoformat())
    except OSError as exc:
        logger.warning("cannot write %s: %s", stamp, exc)
    return True


def warm_run(fmu_dir: str | None = None) -> int:
    """The warm-up itself (in a fresh interpreter): the whole default scene, every FMU in this process
    (those of ``fmu_dir`` when given, else the scene's).

    Some kernels first run late (the non-linear ETMM tensors once the wall strains past their
    threshold, about 0.7 s after the first contact), so a shorter run leaves them to the user's.
    """
    from orchestration.run.simulation import run_scene
    from orchestration.scene.loading import load_scene

    scene_file = SCENE_DIR / "aaa_endovascular.toml"
    with tempfile.TemporaryDirectory(prefix="aaa_cosim_warm_") as tmp:
        if fmu_dir is not None:  # FMU paths resolve next to the scene file first: a copy beside those FMUs
            scene_file = Path(shutil.copy(scene_file, Path(fmu_dir) / f".warm-{os.getpid()}.toml"))
        try:
            scene = load_scene(scene_file)
        finally:
            if fmu_dir is not None:
                scene_file.unlink()
        summary, _ = run_scene(scene, tmp, hosting=Hosting.IN_PROCESS, progress=False, plots=False, vtu=False)
    if summary["status"] != RunStatus.COMPLETED:
        print(summary["error"], file=sys.stderr)
        return 1
    return 0
