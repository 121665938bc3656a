"""docs/foxglove-layout.json: valid JSON whose every plotted path names a channel and field fuelid writes."""
import json
import re
from pathlib import Path

import cantools

from fuelid.ident.live import SCHEMAS
from fuelid.logger.mcap_log import FLOWMETER_SCHEMA

LAYOUT = Path(__file__).resolve().parents[1] / "docs" / "foxglove-layout.json"
DBC = Path(__file__).resolve().parents[1] / "fuelid" / "dbc" / "fms.dbc"


def test_every_plotted_path_exists():
    layout = json.loads(LAYOUT.read_text())
    dbc = cantools.database.load_file(DBC)
    fields = {topic: set(schema["properties"]) for topic, schema in {**SCHEMAS, "/flowmeter": FLOWMETER_SCHEMA}.items()}
    paths = [p["value"] for panel in layout["configById"].values() for p in panel["paths"]]
    assert len(paths) >= 8
    for path in paths:
        m = re.fullmatch(r"(/[\w/]+?)(?:\{sa==\d+\})?\.(\w+)", path)
        assert m, path
        topic, field = m.groups()
        if topic.startswith("/j1939/"):
            assert field in [s.name for s in dbc.get_message_by_name(topic.removeprefix("/j1939/")).signals], path
        else:
            assert field in fields[topic], path
    panels = re.findall(r'"(Plot![a-z]+)"', json.dumps(layout["layout"]))
    assert sorted(panels) == sorted(layout["configById"])  # every panel placed, none missing
