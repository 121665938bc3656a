"""fuelid warmup: compiles and caches the online estimators, and says where the cache is."""
import json

from fuelid.cli import main


def test_warmup_reports_time_and_cache(capsys, monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    assert main(["warmup", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["seconds"] > 0 and "__pycache__" in out["cache"]
    monkeypatch.setenv("NUMBA_CACHE_DIR", "/var/cache/fuelid-numba")  # only reported: numba read it at import
    assert main(["warmup"]) == 0
    assert "/var/cache/fuelid-numba" in capsys.readouterr().out
