"""The Dataset cache in the user cache directory (ident.datacache): a second build with the same files and
options is read back, identical; any other byte, option or file list builds again; nothing is written beside the
recordings, nor anything on a failed build; the directory stays under its bound, least recently used first; a
directory that cannot be written means no cache; it can be turned off."""
import os
import warnings

import pytest

from fuelid.cli import main
from fuelid.errors import FuelidError
from fuelid.ident.datacache import cache_dir, cache_key, cache_path, cached_dataset
from fuelid.ident.dataset import build_dataset
from tests.ident.test_dataset_columns import assert_same
from tests.ident.test_dataset_mcap import recording, write_mcap


@pytest.fixture(autouse=True)
def cache_on(monkeypatch, tmp_path):
    monkeypatch.delenv("FUELID_DATASET_CACHE")  # tests/conftest.py turns it off for every other test
    monkeypatch.setenv("FUELID_CACHE_DIR", str(tmp_path / "cache"))


def cached(paths, options) -> bool:
    return cache_path(cache_key(list(paths), options)).is_file()


def beside(mcap) -> list[str]:
    """Files in the recording's folder other than recordings and what a test writes there."""
    return sorted(p.name for p in mcap.parent.iterdir() if not p.name.endswith((".mcap", ".csv", ".json")) and p.name != "cache")


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
    assert built == 1 and cached([mcap], {"Ts": 0.3}) and beside(mcap) == []
    again, built = counted([mcap], {"Ts": 0.3})
    assert built == 0
    assert_same(again, first)


def test_another_byte_option_or_file_list_builds_again(mcap, tmp_path):
    counted([mcap], {"Ts": 0.3})
    assert counted([mcap], {"Ts": 0.2})[1] == 1  # another option
    lagged, built = counted([mcap], {"Ts": 0.2, "fuel_lag_s": 0.1})
    assert built == 1 and counted([mcap], {"Ts": 0.2, "fuel_lag_s": 0.1})[0].fuel_lag_s == 0.1 == lagged.fuel_lag_s
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
    cache_path(cache_key([mcap], {})).write_bytes(b"not a cache")
    ds, built = counted([mcap], {})
    assert built == 1
    assert_same(counted([mcap], {})[0], ds)


def test_turned_off_or_unwritable_it_builds_and_writes_nothing(mcap, monkeypatch):
    assert counted([mcap], {}, enabled=False)[1] == 1 and not cached([mcap], {})
    monkeypatch.setenv("FUELID_DATASET_CACHE", "0")
    assert counted([mcap], {})[1] == 1 and not cached([mcap], {})
    monkeypatch.delenv("FUELID_DATASET_CACHE")
    assert counted([mcap], {})[1] == 1 and cached([mcap], {})
    monkeypatch.setenv("FUELID_CACHE_DIR", str(mcap))  # a file where the directory should be: no cache
    assert counted([mcap], {})[1] == 1 and counted([mcap], {})[1] == 1
    readonly = mcap.parent / "readonly"
    readonly.mkdir(mode=0o555)
    monkeypatch.setenv("FUELID_CACHE_DIR", str(readonly / "fuelid"))
    try:
        if os.access(readonly, os.W_OK):
            pytest.skip("running as a user who writes into read-only folders")
        assert counted([mcap], {})[1] == 1 and not (readonly / "fuelid").exists()
    finally:
        os.chmod(readonly, 0o755)


def test_the_user_cache_directory_by_default(monkeypatch, tmp_path):
    monkeypatch.delenv("FUELID_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "fuelid"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache_dir() == tmp_path / "home" / ".cache" / "fuelid"


def test_a_failed_build_leaves_nothing(mcap):
    def fails():
        raise FuelidError("no fuel signal")
    with pytest.raises(FuelidError):
        cached_dataset([mcap], {}, fails)
    assert not cache_dir().exists() or list(cache_dir().iterdir()) == []
    assert beside(mcap) == []


def test_the_directory_stays_under_its_bound_least_recently_used_first(mcap, monkeypatch):
    counted([mcap], {"Ts": 0.3})
    size = cache_path(cache_key([mcap], {"Ts": 0.3})).stat().st_size
    monkeypatch.setenv("FUELID_CACHE_MAX_MB", str(2.5 * size / 1e6))  # room for two
    counted([mcap], {"Ts": 0.2})
    os.utime(cache_path(cache_key([mcap], {"Ts": 0.3})), (1, 1))
    os.utime(cache_path(cache_key([mcap], {"Ts": 0.2})), (2, 2))
    assert counted([mcap], {"Ts": 0.3})[1] == 0  # a hit: now the most recently used
    counted([mcap], {"Ts": 0.25})  # a third: the least recently used (Ts 0.2) goes
    assert cached([mcap], {"Ts": 0.3}) and cached([mcap], {"Ts": 0.25}) and not cached([mcap], {"Ts": 0.2})
    assert sum(p.stat().st_size for p in cache_dir().iterdir()) <= 2.5 * size


def test_the_dataset_command_uses_it_unless_told_not_to(mcap, tmp_path):
    assert main(["dataset", str(mcap), "-o", str(tmp_path / "a.csv"), "--no-cache"]) == 0
    assert not cache_dir().exists()
    assert main(["dataset", str(mcap), "-o", str(tmp_path / "a.csv")]) == 0
    assert len(list(cache_dir().glob("*.npz"))) == 1 and beside(mcap) == []
    before = (tmp_path / "a.csv").read_text()
    assert main(["dataset", str(mcap), "-o", str(tmp_path / "b.csv")]) == 0
    assert (tmp_path / "b.csv").read_text().split("\n", 1)[1] == before.split("\n", 1)[1]
