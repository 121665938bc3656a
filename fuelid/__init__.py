"""fuelid: truck CAN logger and fuel-flow model identification."""
from fuelid.blas import pin_kernels

pin_kernels()  # before numpy loads OpenBLAS: the same models on every x86-64 CPU (fuelid.blas)

__version__ = "0.1.0"
