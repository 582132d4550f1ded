"""``python -m orchestration.studies NAME [--quick] [--workers N] ...``: a study, as
``python -m orchestration study NAME ...`` runs it (the same options and exit codes)."""
import sys

from orchestration.app.cli import main

sys.exit(main(["study", *sys.argv[1:]]))
