"""The documentation: the site builds in strict mode, the FMU reference is current, and the
README's commands are the ones that run.

- The site (mkdocs.yml, docs/) builds with ``mkdocs build --strict``: a broken link or anchor, a
  page missing from the nav, any warning fails.
- The FMU reference pages (docs/fmus/) are what tools/fmu_reference.py makes of the FMUs'
  declarations today.
- The README's install and test commands are those .ci/run runs (CI runs the README), its command
  summary names only options the command line has, and its C importer example compiles and runs.
"""
from __future__ import annotations

import importlib.util
import os
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
CI_RUN = REPO / ".ci" / "run"


def _load_tool(name: str):
    spec = importlib.util.spec_from_file_location(f"docs_tool_{name}", REPO / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


fmu_reference = _load_tool("fmu_reference")


def _code_blocks(text: str) -> list[tuple[str, str]]:
    """The fenced code blocks of a markdown text: (language, body)."""
    return re.findall(r"^```(\w*)\n(.*?)^```", text, flags=re.S | re.M)


# -- the site -----------------------------------------------------------------------------------
def test_the_site_builds_in_strict_mode_without_a_warning(tmp_path):
    site = tmp_path / "site"
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}  # mkdocs-material's notice about its successor
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
                           str(REPO / "mkdocs.yml"), "--site-dir", str(site)],
                          cwd=REPO, capture_output=True, text=True, env=env, timeout=300)
    log = proc.stdout + proc.stderr
    problems = [line for line in log.splitlines() if re.match(r"\s*(WARNING|ERROR)\b", line)]
    assert proc.returncode == 0 and not problems, f"mkdocs build --strict failed:\n{log[-5000:]}"
    # the changelog (CHANGELOG.md at the root) is in the site, its links rewritten for it
    changelog = (site / "changelog" / "index.html").read_text(encoding="utf-8")
    first_entry = re.search(r"^## (.+)$", (REPO / "CHANGELOG.md").read_text(encoding="utf-8"), re.M).group(1)
    assert first_entry.split(":")[0] in changelog
    for page in ("fmus/tissue", "fmus/contact", "fmus/catheter", "coupling", "design", "scenes"):
        assert (site / page / "index.html").exists(), page


def test_the_changelog_links_are_rewritten_for_the_site():
    hooks = _load_tool("mkdocs_hooks")
    text = ("[a](docs/ports.md#contact) [b](README.md#commands) [c](docs/) [d](scenes/README.md) "
            "[e](tests/test_docs.py) [f](https://example.org/x.md) [g](#top)")
    assert hooks.rewrite_links(text) == ("[a](ports.md#contact) [b](index.md) [c](index.md) [d](scenes.md) "
                                         "e [f](https://example.org/x.md) [g](#top)")


# -- the FMU reference ----------------------------------------------------------------------------
def test_the_fmu_reference_is_generated_from_the_current_declarations():
    pages = fmu_reference.render(fmu_reference.declarations())
    outdated = [str(path.relative_to(REPO)) for path in fmu_reference.stale(pages)]
    assert not outdated, (f"out of date with the FMUs' declarations: {', '.join(outdated)}; "
                          f"regenerate with `{fmu_reference.REGENERATE}`")
    leftover = sorted(set(fmu_reference.OUT_DIR.glob("*.md")) - set(pages))
    assert not leftover, f"pages of no FMU (remove them, and from mkdocs.yml's nav): {leftover}"


def test_the_reference_writes_numbers_as_a_reader_does():
    number = fmu_reference.number
    assert [number(x) for x in (1120.0, 0.45, 1.044e6, 1e-6, 1e10, -1e4, 0.0, 1 / 30)] == [
        "1120", "0.45", "1.044e6", "1e-6", "1e10", "-10000", "0", "0.03333333333333333"]
    assert [number(x, integer=True) for x in (2_000_000, 31, 1e6)] == ["2e6", "31", "1e6"]
    assert [fmu_reference.seconds(x) for x in (1 / 30, 0.001, 0.5)] == ["1/30", "0.001", "0.5"]


def test_the_docs_extra_and_the_test_extra_pin_the_same_tools():
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    docs = set(extras["docs"])
    assert docs and all("==" in pin for pin in docs)
    assert docs <= set(extras["test"]), f"the test extra lacks {sorted(docs - set(extras['test']))}"


# -- the README's commands ------------------------------------------------------------------------
def _normalized(command: str) -> tuple[str, ...]:
    """A command's words without what only changes how much it prints (``-q``), and pip by one
    name (``.venv/bin/pip`` is ``.venv/bin/python -m pip``)."""
    words = shlex.split(command)
    if words[:1] == [".venv/bin/pip"]:
        words = [".venv/bin/python", "-m", "pip", *words[1:]]
    return tuple(w for w in words if w not in ("-q", "--quiet"))


def _ci_commands() -> dict[str, tuple[str, ...]]:
    """What .ci/run runs: the venv, the install (with the extras it installs when it can), the tests."""
    lines = [line.strip() for line in CI_RUN.read_text().splitlines()]
    lines = [line for line in lines if line and not line.startswith("#")]
    assignments = [re.fullmatch(r'extras="([^"]*)"', line) for line in lines]
    extras = [m.group(1) for m in assignments if m]
    commands = {"extras": tuple(extras)}
    for line in lines:
        if line.startswith("python3 -m venv"):
            commands["venv"] = _normalized(line)
        elif "pip install" in line and " -e " in line:
            commands["install"] = _normalized(line.replace("$extras", extras[0]))
        elif "-m pytest" in line:
            commands["test"] = _normalized(line)
    assert {"venv", "install", "test"} <= set(commands) and extras, \
        f"cannot find the venv, install and test commands in {CI_RUN}: the parsing here needs updating"
    return commands


def _commands_in(page: Path) -> dict[str, tuple[str, ...]]:
    """The first venv, install and test commands in the code blocks of ``page``."""
    commands = {}
    for language, body in _code_blocks(page.read_text()):
        for part in (p.strip() for p in body.replace("\n", " && ").split("&&")):
            if part.startswith("python3 -m venv"):
                commands.setdefault("venv", _normalized(part))
            elif "pip install" in part and " -e " in part:
                commands.setdefault("install", _normalized(part))
            elif "-m pytest" in part:
                commands.setdefault("test", _normalized(part))
    return commands


@pytest.mark.parametrize("page", ["README.md", "docs/getting-started.md"])
def test_the_install_and_test_commands_are_those_ci_runs(page):
    ci, written = _ci_commands(), _commands_in(REPO / page)
    for what in ("venv", "install", "test"):
        assert written.get(what) == ci[what], (
            f"the {what} command of {page} drifted from .ci/run's (CI runs the README's setup):\n"
            f"  {page}: {' '.join(written.get(what, ('(none found)',)))}\n"
            f"  .ci/run: {' '.join(ci[what])}\n"
            "make them the same again (quiet flags and `.venv/bin/pip` for `.venv/bin/python -m pip` aside)")
    text = (REPO / page).read_text()
    default, *fallback = ci["extras"]
    for extras in fallback:  # the README's fallback is the one .ci/run takes
        assert f'".[{extras}]" instead of ".[{default}]"' in text.replace("`", ""), \
            f'.ci/run falls back to ".[{extras}]": {page} should say so'
    for package in re.search(r"for package in ([^;]+);", CI_RUN.read_text()).group(1).split():
        assert f" {package}" in text, f".ci/run installs {package}; the apt-get line of {page} should name it"


def _command_summary() -> list[str]:
    text = README.read_text()
    section = text[text.index("## Commands"):]
    language, body = _code_blocks(section)[0]
    lines = [line.strip() for line in body.splitlines() if line.strip()]
    # an option list continued on the next line belongs to the command above it
    joined: list[str] = []
    for line in lines:
        if line.startswith("python -m orchestration"):
            joined.append(line)
        else:
            joined[-1] += " " + line
    return joined


def _help(*words: str) -> str:
    proc = subprocess.run([sys.executable, "-m", "orchestration", *words, "--help"], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_the_readme_command_summary_names_only_what_the_command_line_has():
    summary = _command_summary()
    subcommands = {line.split()[3] for line in summary}
    top = _help()
    listed = set(re.search(r"\{([a-z,-]+)\}", top).group(1).split(","))
    assert subcommands == listed, f"README lists {sorted(subcommands)}, the command line has {sorted(listed)}"
    for line in summary:
        words = line.split()
        command = words[3]
        help_text = _help(command)
        for option in re.findall(r"--[a-z][a-z-]*", line):
            assert option in help_text, f"README: `{command} {option}` is not an option of `{command}`"
        for choices in re.findall(r"\b([a-z-]+(?:\|[a-z-]+)+)\b", " ".join(words[4:])):
            for choice in choices.split("|"):
                assert choice in help_text, f"README: `{command}` has no choice {choice!r}"
        if command == "build":
            names = re.search(r"\[([A-Z][A-Za-z ]+)\]", line).group(1).split()
            specs, _ = fmu_reference._build_side()
            assert sorted(names) == sorted(specs), f"README builds {names}, the build knows {sorted(specs)}"


def test_the_readme_names_the_shipped_scenes():
    text = README.read_text()
    named = re.search(r"`SCENE` is a shipped scene name \(([^)]*)\)", text).group(1)
    assert sorted(re.findall(r"`([a-z_]+)`", named)) == sorted(p.stem for p in (REPO / "scenes").glob("*.toml"))


def test_the_readme_c_importer_example_compiles_and_runs(catheter_fmu, tmp_path):
    """The README's two commands as written, in a folder that has the repository's src/ and tests/
    and an fmus/ with the Catheter FMU this session built (the FMU extracted into tmp_path)."""
    if shutil.which("cc") is None:
        pytest.skip("no C compiler `cc` (the README's example needs one)")
    text = README.read_text()
    example = text[text.index("with the small C importer"):]
    compile_line, run_line = _code_blocks(example)[0][1].strip().splitlines()
    for name in ("src", "tests"):
        (tmp_path / name).symlink_to(REPO / name)
    (tmp_path / "fmus").mkdir()
    (tmp_path / "fmus" / "Catheter.fmu").symlink_to(catheter_fmu)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "LD_PRELOAD")}
    proc = subprocess.run(shlex.split(compile_line), cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, f"README: `{compile_line}` failed:\n{proc.stderr[-3000:]}"
    words = shlex.split(run_line)
    words[2] = str(tmp_path / "extracted")  # the folder the host extracts the FMU into
    try:
        proc = subprocess.run(words, cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)
    finally:
        shutil.rmtree(tmp_path / "extracted", ignore_errors=True)
    assert proc.returncode == 0, f"README: `{run_line}` failed:\n{proc.stderr[-3000:]}"
    assert "run completed" in proc.stdout, proc.stdout[-2000:]
    tip = [line.split() for line in proc.stdout.splitlines() if line.startswith("tip_position")]
    assert tip and len(tip[-1]) == 4, proc.stdout[-2000:]
