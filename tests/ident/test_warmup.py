"""ident.warmup: after compile_estimators, `fuelid online` (from scratch, or Kalman from a prior) compiles nothing."""
import os
from pathlib import Path

from fuelid.cli import main
from fuelid.ident import kalman, rpem
from fuelid.ident.warmup import compile_estimators

SAMPLE = Path(__file__).resolve().parents[2] / "replay_logs" / "sample_diesel_1min.log.gz"
ENTRY_POINTS = (rpem._run, kalman._track)  # every other kernel is compiled into these


def test_online_commands_compile_nothing_after_warmup(tmp_path):
    assert compile_estimators() > 0
    compiled = [list(f.signatures) for f in ENTRY_POINTS]
    assert all(len(sigs) == 1 for sigs in compiled)
    assert all(os.path.exists(f._cache._cache_file._index_path) for f in ENTRY_POINTS)  # cached on disk
    mcap, scratch = tmp_path / "trip.mcap", tmp_path / "scratch.json"
    assert main(["convert", str(SAMPLE), "-o", str(mcap)]) == 0
    assert main(["online", str(mcap), "-o", str(scratch)]) == 0
    assert main(["online", str(mcap), "--prior", str(scratch), "--method", "kalman", "-o",
                 str(tmp_path / "kalman.json")]) == 0
    assert [list(f.signatures) for f in ENTRY_POINTS] == compiled
