"""The Dataset cache beside the recordings (ident.datacache): a second build with the same files and options
is read back, identical; any other byte, option or file list builds again; it can be turned off."""
import os
import warnings

import pytest

from fuelid.cli import main
from fuelid.errors import FuelidError
from fuelid.ident.datacache import cache_path, cached_dataset
from fuelid.ident.dataset import build_dataset
from tests.ident.test_dataset_columns import assert_same
from tests.ident.test_dataset_mcap import recording, write_mcap


@pytest.fixture(autouse=True)
def cache_on(monkeypatch):
    monkeypatch.delenv("FUELID_DATASET_CACHE")  # tests/conftest.py turns it off for every other test


@pytest.fixture
def mcap(tmp_path):
    return write_mcap(tmp_path / "a.mcap", recording(1_700_000_000.0, 60.0, 1))


def counted(paths, options, **kwargs):
    builds = []

    def build():
        builds.append(1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            return build_dataset(paths, **options)
    return cached_dataset(paths, options, build, **kwargs), len(builds)


def test_the_second_build_is_read_back_identical(mcap):
    first, built = counted([mcap], {"Ts": 0.3})
    assert built == 1 and cache_path(mcap).is_file()
    again, built = counted([mcap], {"Ts": 0.3})
    assert built == 0
    assert_same(again, first)


def test_another_byte_option_or_file_list_builds_again(mcap, tmp_path):
    counted([mcap], {"Ts": 0.3})
    assert counted([mcap], {"Ts": 0.2})[1] == 1  # another option
    other = write_mcap(tmp_path / "b.mcap", recording(1_700_000_300.0, 30.0, 2))
    assert counted([mcap, other], {"Ts": 0.2})[1] == 1  # another file list
    data = bytearray(mcap.read_bytes())
    stat = mcap.stat()
    data[len(data) // 2] ^= 1  # one bit of one message, the file's size and times kept
    mcap.write_bytes(bytes(data))
    os.utime(mcap, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    try:
        built = counted([mcap, other], {"Ts": 0.2})[1]
    except FuelidError:  # the bit was in a chunk: built again, which finds the damage
        built = 1
    assert built == 1


def test_a_cache_file_that_does_not_load_is_rebuilt(mcap):
    counted([mcap], {})
    cache_path(mcap).write_bytes(b"not a cache")
    ds, built = counted([mcap], {})
    assert built == 1
    assert_same(counted([mcap], {})[0], ds)


def test_turned_off_or_unwritable_it_builds_and_writes_nothing(mcap, monkeypatch):
    assert counted([mcap], {}, enabled=False)[1] == 1 and not cache_path(mcap).exists()
    monkeypatch.setenv("FUELID_DATASET_CACHE", "0")
    assert counted([mcap], {})[1] == 1 and not cache_path(mcap).exists()
    monkeypatch.delenv("FUELID_DATASET_CACHE")
    assert counted([mcap], {})[1] == 1 and cache_path(mcap).exists()
    cache_path(mcap).unlink()
    os.chmod(mcap.parent, 0o555)
    try:
        if os.access(mcap.parent, os.W_OK):
            pytest.skip("running as a user who writes into read-only folders")
        assert counted([mcap], {})[1] == 1 and not cache_path(mcap).exists()
    finally:
        os.chmod(mcap.parent, 0o755)


def test_the_dataset_command_uses_it_unless_told_not_to(mcap, tmp_path):
    assert main(["dataset", str(mcap), "-o", str(tmp_path / "a.csv"), "--no-cache"]) == 0
    assert not cache_path(mcap).exists()
    assert main(["dataset", str(mcap), "-o", str(tmp_path / "a.csv")]) == 0
    assert cache_path(mcap).exists()
    before = (tmp_path / "a.csv").read_text()
    assert main(["dataset", str(mcap), "-o", str(tmp_path / "b.csv")]) == 0
    assert (tmp_path / "b.csv").read_text().split("\n", 1)[1] == before.split("\n", 1)[1]
