"""`fuelid recover` end to end through the CLI's own error handling."""
import json

import pytest

from fuelid import cli
from fuelid.logger.mcap_log import RAW_SCHEMA, McapLogWriter, read_messages


@pytest.fixture
def cut_log(tmp_path):
    path = tmp_path / "trip.mcap"
    with McapLogWriter(path, metadata={"truck": "T1"}, fsync=False) as w:
        w.add_channel("/can/raw", RAW_SCHEMA)
        for i in range(100):
            w.write("/can/raw", i * 100_000_000, {"t": i / 10})
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def test_recover_json(cut_log, capsys):
    assert cli.main(["recover", str(cut_log), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    fixed = cut_log.with_name("trip.recovered.mcap")
    assert out["output"] == str(fixed) and not out["complete"] and out["bytes_lost"] > 0
    assert out["messages"]["/can/raw"] == out["message_count"] == len(list(read_messages(fixed)))
    assert 20 <= out["message_count"] < 100


def test_recover_text(cut_log, tmp_path, capsys):
    assert cli.main(["recover", str(cut_log), "-o", str(tmp_path / "fixed.mcap")]) == 0
    out = capsys.readouterr().out
    assert "was truncated" in out and "/can/raw" in out


def test_recover_garbage_is_one_line_on_stderr(tmp_path, capsys):
    bad = tmp_path / "bad.mcap"
    bad.write_text("not mcap")
    assert cli.main(["recover", str(bad)]) == 1
    err = capsys.readouterr().err
    assert err.strip() == f"fuelid recover: error: not an MCAP file: {bad}"
