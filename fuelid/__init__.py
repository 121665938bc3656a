"""fuelid: truck CAN logger and fuel-flow model identification."""

__version__ = "0.1.0"
