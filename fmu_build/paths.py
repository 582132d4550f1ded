"""Where the build reads sources and writes FMUs and intermediate files."""
from __future__ import annotations

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
SRC = REPO_ROOT / "src"
LAYER = SRC / "fmi3_layer"
#: The project's built FMUs, where scenes find them by default.
DEFAULT_FMU_DIR = REPO_ROOT / "fmus"
BUILD_DIR = REPO_ROOT / "build"
SCENE_DIR = REPO_ROOT / "scenes"
PLATFORM = "x86_64-linux"
