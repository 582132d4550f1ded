"""A clean Debian root filesystem to run things in, for the tests that an FMU is portable.

An FMU is meant to run on a machine that has nothing of this project: no venv, no Python, no
compiler, no user caches. The nearest such machine at hand is a root filesystem made by
``debootstrap --variant=minbase`` (the essential packages only: libc, coreutils, dash, ...) of the
distribution this machine runs, entered with ``chroot``. Nothing of the build machine is visible
in it but the files a test copies in.

* :func:`clean_rootfs` makes that root filesystem once and caches it between runs (about half a
  minute and 200 MB the first time, with a fast mirror); when it cannot be made the calling test
  is skipped with the reason and what to do about it.
* :func:`run_in_rootfs` runs a command in it, in a fresh folder holding only the given files, with
  a minimal environment, and removes the folder afterwards.
* :func:`c_host_files` is what the C importer (tests/c_host/fmu_host.c) needs in there: the binary
  and any shared library it links that the root filesystem lacks; :func:`c_host_argv` runs it.

The command runs in private mount and PID namespaces (``unshare``) with its own ``/proc`` mounted,
as on any real machine (Python and its libraries read ``/proc``); the mount disappears with the
namespace, so nothing is ever left mounted in the cached tree. Where ``unshare`` is not permitted
the command runs in a bare ``chroot`` without ``/proc`` (logged as a warning).
"""
from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import re
import secrets
import shutil
import subprocess
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

log = logging.getLogger(__name__)

MIRRORS = {"debian": "http://deb.debian.org/debian", "ubuntu": "http://archive.ubuntu.com/ubuntu"}
MARKER = ".aaa-cosim-rootfs-complete"  # written into the tree only after debootstrap succeeded
BUILD_TIMEOUT = 1800.0  # seconds for debootstrap: downloads ~50 MB and unpacks ~100 packages
# Folders of a root filesystem the dynamic loader searches by default (x86_64 Debian/Ubuntu and
# the generic ones); those of its /etc/ld.so.conf.d are added in _library_folders.
LIBRARY_FOLDERS = ("lib", "lib64", "usr/lib", "usr/lib64", "lib/x86_64-linux-gnu", "usr/lib/x86_64-linux-gnu",
                   "usr/local/lib")
HOST_LIBS = "host-libs"  # folder, beside the C host in the run folder, of the libraries the rootfs lacks
MINIMAL_PATH = "/usr/bin:/bin"


# -- the root filesystem -----------------------------------------------------------------------------


def _os_release() -> dict[str, str]:
    fields = {}
    with contextlib.suppress(OSError):
        for line in Path("/etc/os-release").read_text().splitlines():
            key, sep, value = line.partition("=")
            if sep:
                fields[key.strip()] = value.strip().strip('"')
    return fields


def rootfs_path(codename: str) -> Path:
    """Where the root filesystem is cached: ``$AAA_COSIM_ROOTFS``, else under the user's cache."""
    if os.environ.get("AAA_COSIM_ROOTFS"):
        return Path(os.environ["AAA_COSIM_ROOTFS"]).expanduser().absolute()
    return Path.home() / ".cache" / "aaa-cosim" / "rootfs" / f"{codename}-minbase"


def _mount_points_under(folder: Path) -> list[str]:
    """Mount points at or below ``folder`` (a killed debootstrap can leave its /proc, /sys mounted)."""
    prefix = str(folder.resolve())
    points = []
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/mountinfo").read_text().splitlines():
            point = line.split()[4].replace("\\040", " ")
            if point == prefix or point.startswith(prefix + "/"):
                points.append(point)
    return points


def _remove_tree(folder: Path) -> None:
    """Removes a (partial) root filesystem. Whatever is still mounted in it is unmounted first, and
    ``rm --one-file-system`` never descends into a mount: a bind mount of the host's /dev left by a
    killed debootstrap must not cost the host its device nodes."""
    for point in sorted(_mount_points_under(folder), key=len, reverse=True):
        subprocess.run(["umount", "--lazy", point], capture_output=True)
    subprocess.run(["rm", "-rf", "--one-file-system", str(folder)], capture_output=True)
    if folder.exists():
        log.warning("could not remove %s entirely (something still mounted in it?)", folder)


def _mirror_reachable(mirror: str, codename: str) -> str | None:
    """None when the mirror serves the distribution's Release file, else why not."""
    url = f"{mirror}/dists/{codename}/Release"
    try:
        with urllib.request.urlopen(url, timeout=20) as response:
            response.read(1)
        return None
    except (urllib.error.URLError, OSError) as error:
        return f"{url}: {error}"


def _chroot_works(root: Path) -> str | None:
    """None when ``chroot`` into ``root`` runs a program, else the error."""
    try:
        result = subprocess.run([_tool("chroot"), str(root), "/bin/true"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as error:
        return str(error)
    return None if result.returncode == 0 else (result.stderr.strip() or f"exit status {result.returncode}")


def _tree_size(root: Path) -> int:
    result = subprocess.run(["du", "-sxb", str(root)], capture_output=True, text=True)
    return int(result.stdout.split()[0]) if result.returncode == 0 and result.stdout else 0


def _build(final: Path, codename: str, mirror: str) -> None:
    """debootstrap into a temporary sibling of ``final``, renamed into place only on success (with
    the marker already in it), so that a build that crashes or is killed never leaves a tree that
    a later run takes for a good one; such leftovers are removed by the next build."""
    for stale in final.parent.glob(f"{final.name}.building-*"):
        log.info("removing the leftover of an interrupted build: %s", stale)
        _remove_tree(stale)
    if final.exists():  # without the marker: not a tree we finished; not ours to delete either
        pytest.skip(f"{final} exists but is not a finished root filesystem (no {MARKER} in it): "
                    f"remove it, or point AAA_COSIM_ROOTFS elsewhere")
    unreachable = _mirror_reachable(mirror, codename)
    if unreachable:
        pytest.skip(f"cannot build the clean root filesystem: the mirror is unreachable ({unreachable}); "
                    f"connect to the network once (the tree is cached in {final} afterwards) or set "
                    f"AAA_COSIM_ROOTFS to one built before")
    building = Path(tempfile.mkdtemp(prefix=f"{final.name}.building-", dir=final.parent))
    building.chmod(0o755)  # mkdtemp makes it 0700: the root folder of a system is 0755
    log_file = final.parent / f"{final.name}.debootstrap.log"
    command = ["debootstrap", "--variant=minbase", codename, str(building), mirror]
    log.info("building the clean root filesystem (first run only): %s", " ".join(command))
    started = time.monotonic()
    try:
        with log_file.open("w") as output:
            result = subprocess.run(command, stdout=output, stderr=subprocess.STDOUT, timeout=BUILD_TIMEOUT)
        if result.returncode != 0:
            tail = "\n".join(log_file.read_text(errors="replace").splitlines()[-15:])
            pytest.skip(f"debootstrap failed (exit status {result.returncode}; whole log in {log_file}):\n{tail}")
        (building / MARKER).write_text(f"{' '.join(command)}\nbuilt in {time.monotonic() - started:.0f} s\n")
        building.rename(final)
    except subprocess.TimeoutExpired:
        pytest.skip(f"debootstrap took more than {BUILD_TIMEOUT:.0f} s (log in {log_file})")
    finally:
        if building.exists():
            _remove_tree(building)
    log.info("clean root filesystem built in %.0f s: %s (%.0f MB)", time.monotonic() - started, final,
             _tree_size(final) / 1e6)


def clean_rootfs() -> Path:
    """The cached minbase root filesystem of this machine's distribution, built on first use.

    Skips the calling test, saying why and what to do, when it cannot be had: not root (debootstrap
    and chroot need it), no debootstrap, not Debian or Ubuntu, the mirror unreachable, debootstrap
    failing, or chroot not permitted (a container without CAP_SYS_CHROOT). An ``fcntl`` lock next
    to the tree keeps two pytest processes (xdist workers, two terminals) from building it twice.
    """
    release = _os_release()
    distribution, codename = release.get("ID", ""), release.get("VERSION_CODENAME", "")
    if distribution not in MIRRORS or not codename:
        pytest.skip(f"a clean root filesystem is made for Debian or Ubuntu only; this machine runs "
                    f"{release.get('PRETTY_NAME', 'an unknown system')} (no ID/VERSION_CODENAME in /etc/os-release)")
    final = rootfs_path(codename)
    if not (final / MARKER).is_file():
        if os.geteuid() != 0:
            pytest.skip(f"building the clean root filesystem {final} needs root (debootstrap, chroot): "
                        f"run the tests as root, e.g. in a container")
        if shutil.which("debootstrap") is None:
            pytest.skip("debootstrap is not installed: apt-get install debootstrap")
        final.parent.mkdir(parents=True, exist_ok=True)
        with open(final.parent / f"{final.name}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, also when this process dies
            if not (final / MARKER).is_file():  # another process may have built it while we waited
                _build(final, codename, MIRRORS[distribution])
    if os.geteuid() != 0:
        pytest.skip(f"running in the clean root filesystem {final} needs root (chroot)")
    if shutil.which("chroot") is None:
        pytest.skip("chroot is not on PATH (coreutils' /usr/sbin/chroot): add /usr/sbin to PATH")
    refused = _chroot_works(final)
    if refused:
        pytest.skip(f"chroot into {final} is not permitted here ({refused}); a container needs "
                    f"CAP_SYS_CHROOT (docker run --cap-add SYS_CHROOT)")
    _remove_stale_runs(final)
    return final


def _remove_stale_runs(root: Path, age: float = 6 * 3600.0) -> None:
    """Run folders left in the cached tree by a pytest that was killed (each holds an FMU of some
    hundred MB); only old ones, since another pytest process may be running in its own right now."""
    for folder in (root / "tmp").glob("run-*"):
        with contextlib.suppress(OSError):
            if time.time() - folder.stat().st_mtime > age:
                log.info("removing a run folder left by an interrupted test: %s", folder)
                shutil.rmtree(folder, ignore_errors=True)


# -- running in it -----------------------------------------------------------------------------------


_unshare_works: dict[Path, bool] = {}


def _tool(name: str) -> str:
    """A host program by absolute path (the command's environment has no PATH of the build machine's)."""
    search = os.pathsep.join([os.environ.get("PATH", os.defpath), "/usr/sbin", "/sbin"])
    return shutil.which(name, path=search) or name


def _private_proc(root: Path) -> bool:
    """Whether commands can run in ``root`` with a /proc of their own (``unshare`` permitted)."""
    if root not in _unshare_works:
        try:
            probe = subprocess.run([_tool("unshare"), "--mount", "--pid", "--fork", f"--mount-proc={root}/proc",
                                    _tool("chroot"), str(root), "/bin/test", "-r", "/proc/self/status"],
                                   capture_output=True, text=True, timeout=60)
            refused = None if probe.returncode == 0 else probe.stderr.strip() or f"exit status {probe.returncode}"
        except (OSError, subprocess.TimeoutExpired) as error:
            refused = str(error)
        _unshare_works[root] = refused is None
        if refused:
            log.warning("unshare is not permitted here (%s): commands run in %s without /proc", refused, root)
    return _unshare_works[root]


def run_in_rootfs(rootfs: Path, files: dict[Path, str], argv: list[str], timeout: float) -> subprocess.CompletedProcess:
    """Runs ``argv`` in ``rootfs``, in a fresh folder ``/tmp/run-<random>`` holding only ``files``.

    ``files`` maps a host file to its path relative to that folder (copied with its mode). The
    command starts in that folder (relative paths in ``argv`` are relative to it) with the minimal
    environment of a fresh login: PATH=/usr/bin:/bin, HOME=the run folder, LANG=C.UTF-8 and
    nothing else, so no PYTHONPATH, PYTHONHOME, LD_LIBRARY_PATH or VIRTUAL_ENV leaks in from the
    build machine. Its output is captured as text; the folder is removed afterwards, whatever
    happened. Raises ``subprocess.TimeoutExpired`` after ``timeout`` seconds (the namespace's
    processes are killed with it).
    """
    run_name = f"run-{secrets.token_hex(6)}"
    run_dir = Path(rootfs) / "tmp" / run_name
    inside = f"/tmp/{run_name}"
    run_dir.mkdir(mode=0o755)
    try:
        for source, relative in files.items():
            if Path(relative).is_absolute() or ".." in Path(relative).parts:
                raise ValueError(f"{relative!r} is not a path inside the run folder")
            destination = run_dir / relative
            destination.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, destination)
        # env (coreutils) changes to the folder and execs argv: no shell in between to add PWD, OLDPWD
        command = [_tool("chroot"), str(rootfs), "/usr/bin/env", "-i", f"--chdir={inside}", f"PATH={MINIMAL_PATH}",
                   f"HOME={inside}", "LANG=C.UTF-8", *argv]
        if _private_proc(Path(rootfs)):
            # --kill-child: the whole namespace dies with unshare when the timeout kills it
            command = [_tool("unshare"), "--mount", "--pid", "--fork", "--kill-child", f"--mount-proc={rootfs}/proc",
                       *command]
        return subprocess.run(command, capture_output=True, text=True, timeout=timeout, env={"PATH": os.defpath})
    finally:
        shutil.rmtree(run_dir, ignore_errors=True)


# -- the C importer in it ----------------------------------------------------------------------------


def _exists_in(rootfs: Path, path: str) -> bool:
    """Whether ``path`` (absolute, as seen inside ``rootfs``) names an existing file there. Symbolic
    links are followed as the rootfs sees them: an absolute target such as
    ``/usr/lib64/ld-linux-x86-64.so.2 -> /lib/x86_64-linux-gnu/...`` is looked up in the rootfs, not
    on this machine (``Path.exists`` would find the host's file and call a missing one present)."""
    pending, current, hops = [part for part in path.split("/") if part], [], 0
    while pending:
        part = pending.pop(0)
        if part == ".":
            continue
        if part == "..":
            current = current[:-1]
            continue
        candidate = rootfs.joinpath(*current, part)
        if candidate.is_symlink():
            hops += 1
            if hops > 40:
                return False
            target = os.readlink(candidate)
            pending = [p for p in target.split("/") if p] + pending
            if target.startswith("/"):
                current = []
            continue
        if not candidate.exists():
            return False
        current.append(part)
    return True


def _library_folders(rootfs: Path) -> list[str]:
    """The folders (as seen inside ``rootfs``) its dynamic loader searches: the defaults and those
    listed in its /etc/ld.so.conf.d."""
    folders = [f"/{folder}" for folder in LIBRARY_FOLDERS]
    for conf in sorted((rootfs / "etc" / "ld.so.conf.d").glob("*.conf")):
        for line in conf.read_text(errors="replace").splitlines():
            line = line.split("#", 1)[0].strip()
            if line.startswith("/"):
                folders.append(line)
    return folders


def _ldd(binary: Path) -> list[tuple[str, Path | None]]:
    """(name, path on this machine) of each shared object ``binary`` loads, as ``ldd`` lists them:
    ``libz.so.1 => /lib/x86_64-linux-gnu/libz.so.1 (0x...)``, ``/lib64/ld-linux-x86-64.so.2 (0x...)``
    (the loader) and ``linux-vdso.so.1 (0x...)`` (the kernel's, no file: left out)."""
    result = subprocess.run(["ldd", str(binary)], capture_output=True, text=True, check=True)
    libraries = []
    for line in result.stdout.splitlines():
        line = line.strip()
        if match := re.match(r"(\S+) => (\S+) \(0x[0-9a-f]+\)$", line):
            libraries.append((match[1], Path(match[2])))
        elif match := re.match(r"(\S+) => not found$", line):
            libraries.append((match[1], None))
        elif (match := re.match(r"(/\S+) \(0x[0-9a-f]+\)$", line)):  # the dynamic loader, by absolute path
            libraries.append((match[1], Path(match[1])))
    return libraries


def c_host_files(binary: Path, rootfs: Path) -> dict[Path, str]:
    """The C importer and whatever it needs that ``rootfs`` lacks, for :func:`run_in_rootfs`.

    The binary goes to ``fmu_host`` in the run folder; each shared library ``ldd`` lists for it whose
    file name is in none of the rootfs's library folders goes to ``host-libs/`` beside it (the
    dynamic loader too, when the rootfs has none at the path the binary names). :func:`c_host_argv`
    then points the loader at that folder with ``--library-path``, for this process only, rather
    than LD_LIBRARY_PATH, which every process the FMU might start would inherit (the FMU's own
    dlopen calls do search it too, but it holds only what the host brought). In practice the
    host links glibc and libz only, both in minbase, so nothing is added: the run shows that the
    FMU needs nothing beyond what a bare system has.
    """
    binary = Path(binary)
    files = {binary: "fmu_host"}
    folders = _library_folders(Path(rootfs))
    for name, path in _ldd(binary):
        if path is None:
            raise FileNotFoundError(f"{binary} needs {name}, which this machine does not have either")
        if name.startswith("/"):  # the loader: found by its absolute path, not in the search folders
            present = _exists_in(Path(rootfs), name)
        else:
            present = any(_exists_in(Path(rootfs), f"{folder}/{Path(name).name}") for folder in folders)
        if not present:
            log.info("%s is not in the root filesystem: copied beside the C host", name)
            files[path.resolve()] = f"{HOST_LIBS}/{Path(name).name}"
    return files


def c_host_argv(files: dict[Path, str], arguments: list[str]) -> list[str]:
    """The command that runs the C host of :func:`c_host_files` with ``arguments``: ``./fmu_host``,
    or, when libraries were added, through the dynamic loader with ``--library-path host-libs`` (the
    copied loader when the rootfs has none)."""
    added = [relative for relative in files.values() if relative.startswith(f"{HOST_LIBS}/")]
    if not added:
        return ["./fmu_host", *arguments]
    loaders = [relative for relative in added if Path(relative).name.startswith("ld-linux")]
    loader = loaders[0] if loaders else _interpreter(next(source for source, rel in files.items() if rel == "fmu_host"))
    return [loader, "--library-path", HOST_LIBS, "./fmu_host", *arguments]


def _interpreter(binary: Path) -> str:
    """The dynamic loader ``binary`` names (its PT_INTERP), by way of ``ldd``."""
    for name, _ in _ldd(binary):
        if name.startswith("/"):
            return name
    raise RuntimeError(f"{binary} names no dynamic loader (a static binary needs no libraries)")
