"""The project's own J1939/FMS DBC, written from ../shared/design/J1939_FACTS.md."""
from pathlib import Path

FMS_DBC = Path(__file__).with_name("fms.dbc")
