"""The one compiled part of fuelid; everything else is declared in pyproject.toml.

scipy.signal.lfilter's IIR loop with its state in registers, for one signal or two side by side (fuelid/ident/_iir.c,
used by fuelid/ident/filters.py).
Optional: without a C compiler and Python's headers the install goes on, and scipy's own loop gives the same
numbers, slower. -ffp-contract=off: no fused multiply-adds, which would round differently from scipy.
"""
from setuptools import Extension, setup

setup(ext_modules=[Extension("fuelid.ident._iir", ["fuelid/ident/_iir.c"], extra_compile_args=["-ffp-contract=off"],
                             optional=True)])
