"""Command line: ``python -m orchestration build | validate SCENE | run [SCENE] | study NAME``."""
import os
import signal
import sys

# First of all: from here on Ctrl-C and SIGTERM set a flag that the run checks between ticks,
# so that no KeyboardInterrupt can land inside an FMU call or cut the summary short
# (orchestration.stopping). Commands other than "run" give the signals back once parsed.
from orchestration import stopping

stopping.install()

from orchestration.app.cli import main  # noqa: E402 (after the handlers, on purpose)

try:
    code = main()
except BrokenPipeError:
    # The reader of the output went away (`validate SCENE | head`): nothing of ours failed. Point
    # stdout at /dev/null so that the interpreter's final flush does not raise again.
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    code = 1
if stopping.active() is not None:
    # The run is over and its exit code decided. Python restores the default handlers while it
    # shuts down, so a Ctrl-C arriving now would end the process "killed by SIGINT" instead of
    # with that code: ignore them (an ignored signal stays ignored through the shutdown).
    for sig in stopping.STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
sys.exit(code)
