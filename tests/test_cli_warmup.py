"""fuelid warmup: compiles and caches the online estimators, says where the cache is and whether the install built
the offline fits' compiled filter."""
import json

from fuelid.cli import main
from fuelid.ident import filters


def test_warmup_reports_time_and_cache(capsys, monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    assert main(["warmup", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["seconds"] > 0 and "__pycache__" in out["cache"] and out["compiled_filter"] == filters.compiled()
    monkeypatch.setenv("NUMBA_CACHE_DIR", "/var/cache/fuelid-numba")  # only reported: numba read it at import
    assert main(["warmup"]) == 0
    assert "/var/cache/fuelid-numba" in capsys.readouterr().out


def test_warmup_says_when_the_install_built_no_filter(capsys, monkeypatch):
    monkeypatch.setattr(filters, "_iir", None)
    assert main(["warmup"]) == 0
    assert "not compiled (the install found no C compiler" in capsys.readouterr().out
