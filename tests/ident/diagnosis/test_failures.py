"""ident.diagnosis.failures: the sections of where a model fails."""
import numpy as np

from fuelid.ident import diagnosis as dg
from tests.ident import hidden


def test_where_it_fails_sections():
    ds = hidden.make("dpf_regeneration", n=4000, seed=2)
    out = dg.diagnose(hidden.fitted(ds), ds, candidates=())
    worst = out.where_it_fails["worst_segments"]
    assert worst and "DPF active regeneration" in worst[0]["context"]
    emap = out.where_it_fails["error_map"]
    assert np.array(emap["count"]).sum() > 3000 and len(emap["speed_edges_rpm"]) == 9
    white, compared = out.where_it_fails["whiteness"], out.compare["whiteness"]
    assert not white["autocorr_pass"]  # the regeneration is left in the residual
    assert white["autocorr_pass"] == compared["autocorr_pass"]  # one settling rule: the report never says both
    assert white["crosscorr_pass"] == compared["crosscorr_pass"]
    assert out.compare["fit_percent"]["simulation"] > 50
