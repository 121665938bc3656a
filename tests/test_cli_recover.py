"""`fuelid recover` end to end through the CLI's own error handling."""
import json

import pytest
from mcap.reader import make_reader

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


def test_recover_skips_a_damaged_chunk_and_says_what_was_lost(tmp_path, capsys):
    path = tmp_path / "trip.mcap"
    with McapLogWriter(path, metadata={"truck": "T1"}, fsync=False) as w:
        w.add_channel("/can/raw", RAW_SCHEMA)
        for i in range(100):  # 10 chunks of 10 messages
            w.write("/can/raw", i * 100_000_000, {"t": i / 10})
    data = bytearray(path.read_bytes())
    with open(path, "rb") as f:
        fourth = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)[4]
    data[fourth.chunk_start_offset + fourth.chunk_length - 10] ^= 0x20  # inside the chunk at 40 % of the file
    path.write_bytes(bytes(data))
    assert cli.main(["recover", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["damaged"]) == 1 and not out["complete"] and not out["truncated"]
    assert out["message_count"] + out["messages_lost"] == 100 and out["message_count"] >= 80
    assert cli.main(["recover", str(path), "-o", str(tmp_path / "fixed.mcap")]) == 0
    text = capsys.readouterr().out
    d = out["damaged"][0]
    assert "was damaged" in text and f"skipped damaged bytes {d['start']}-{d['end']}" in text
    assert f"{out['messages_lost']} messages lost" in text
