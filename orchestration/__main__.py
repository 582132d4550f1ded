"""Command line: ``python -m orchestration build | validate SCENE | run [SCENE] | study NAME``."""
import sys

# First of all: from here on Ctrl-C and SIGTERM set a flag that the run checks between ticks,
# so that no KeyboardInterrupt can land inside an FMU call or cut the summary short
# (orchestration.stopping). Commands other than "run" give the signals back once parsed.
from .stopping import install

install()

from .cli import main  # noqa: E402 (after the handlers, on purpose)

sys.exit(main())
