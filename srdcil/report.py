"""``python -m srdcil.report RESULTS_DIR [RESULTS_DIR ...] [options]``: the report of run directories.

The entry point only; the code is :mod:`srdcil.analysis.report` (``python -m srdcil.report --help``).
"""
from srdcil.analysis.report import main

if __name__ == "__main__":
    main()
