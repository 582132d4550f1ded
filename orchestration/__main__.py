"""Command line: ``python -m orchestration build | validate SCENE | run [SCENE] | study NAME``."""
import sys

from .cli import main

sys.exit(main())
