"""A wrong path given to any command is one line on stderr naming the path and the cause (fuelid.paths)."""
import pytest

from fuelid.cli import main
from fuelid.logger.mcap_log import McapLogWriter


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Errno" not in err and "os error" not in err
    return err


@pytest.fixture
def recording(tmp_path):
    """An MCAP with engine speed and torque but no fuel signal: a gas truck's bus without its meter capture."""
    path = tmp_path / "gas.mcap"
    with McapLogWriter(path, metadata={}, fsync=False) as w:
        w.add_channel("/j1939/EEC1", {"type": "object"})
        for i in range(100):
            w.write("/j1939/EEC1", i * 10**8, {"t": i * 0.1, "sa": 0, "EngSpeed": 600.0, "ActualEngPercentTorque": 5.0})
    return path


@pytest.mark.parametrize("command", [["identify", "-o", "m.json"], ["convert", "-o", "x.mcap"],
                                     ["dataset", "-o", "d.csv"], ["online", "-o", "m.json"]])
def test_a_folder_given_as_input_is_named_as_a_folder(tmp_path, capsys, command):
    assert main([command[0], str(tmp_path), *[str(tmp_path / a) if "." in a else a for a in command[1:]]]) == 1
    assert one_error_line(capsys) == (f"fuelid {command[0]}: error: {tmp_path}: is a folder, not a file "
                                      f"(give the files in it, e.g. {tmp_path}/*)")


def test_an_output_in_a_missing_folder_names_the_output_not_a_temporary_file(recording, tmp_path, capsys):
    out = tmp_path / "nowhere" / "model.json"
    assert main(["identify", str(recording), "-o", str(out)]) == 1
    assert one_error_line(capsys) == f"fuelid identify: error: {out}: cannot write it: the folder {out.parent} does not exist"
    assert main(["report", str(recording), "-o", str(tmp_path)]) == 1
    assert "is a folder; give the name of the file to write" in one_error_line(capsys)


def test_an_option_naming_a_missing_file_says_so(recording, tmp_path, capsys):
    assert main(["identify", str(recording), "-o", str(tmp_path / "m.json"),
                 "--effects-from", str(tmp_path / "diagnosis.json")]) == 1
    assert one_error_line(capsys).endswith(f"{tmp_path / 'diagnosis.json'}: no such file")


def test_an_os_error_names_its_path(recording, tmp_path, capsys, monkeypatch):
    """A failure past the checks (here: reading is refused) still names the file, in words."""
    import fuelid.commands.dataset as dataset_command

    def refuse(*args, **kw):
        raise PermissionError(13, "Permission denied", str(recording))

    monkeypatch.setattr(dataset_command, "build", refuse)
    assert main(["dataset", str(recording), "-o", str(tmp_path / "d.csv")]) == 1
    assert one_error_line(capsys) == f"fuelid dataset: error: {recording}: Permission denied"


def test_a_gas_trip_without_its_meter_capture_hints_at_flowmeter(recording, tmp_path, capsys):
    assert main(["dataset", str(recording), "-o", str(tmp_path / "d.csv")]) == 1
    assert "--flowmeter CAPTURE.flow" in one_error_line(capsys)
