"""``python -m srdcil.plots {value-maps,ags-contour,vc-diagnostic,chain,run-curve,value-probe} ...``: checkpoint figures.

The entry point only; the code is :mod:`srdcil.analysis.plots` (``python -m srdcil.plots --help``).
"""
from srdcil.analysis.plots import main

if __name__ == "__main__":
    main()
