"""fuelid export: a model.json to a MATLAB script and a .mat file; a bad model is one line on stderr."""
import numpy as np
from scipy.io import loadmat

from fuelid.cli import main
from fuelid.ident.modelfile import save_model
from fuelid.ident.polymodel import PolyModel


def test_export_both_formats(tmp_path, capsys):
    m = PolyModel(A=[1], B=[[0, 0.5], [0.1]], F=[[1, -0.5], [1]], C=[1], D=[1, -0.9], Ts=0.3, nk=(1, 0))
    save_model(m, tmp_path / "model.json")
    assert main(["export", str(tmp_path / "model.json"), "--to", "matlab", "-o", str(tmp_path / "model.m")]) == 0
    assert "sys = idpoly(A, B, C, D, F, NoiseVariance, Ts" in (tmp_path / "model.m").read_text()
    assert main(["export", str(tmp_path / "model.json"), "--to", "mat", "-o", str(tmp_path / "model.mat")]) == 0
    np.testing.assert_array_equal(loadmat(tmp_path / "model.mat")["D"], [[1, -0.9]])
    (tmp_path / "bad.json").write_text("{}")
    assert main(["export", str(tmp_path / "bad.json"), "--to", "mat", "-o", str(tmp_path / "x.mat")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "malformed model" in err and not (tmp_path / "x.mat").exists()
