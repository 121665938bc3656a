"""ident.diagnosis.settings: one frozen object, every threshold documented."""
import ast
import dataclasses
import inspect

import pytest

from fuelid.ident.diagnosis import settings as st


def test_every_threshold_says_what_it_means_and_cannot_be_changed_in_place():
    tree = ast.parse(inspect.getsource(st.Settings))
    body = tree.body[0].body
    documented = {a.target.id for a, doc in zip(body, body[1:])
                  if isinstance(a, ast.AnnAssign) and isinstance(doc, ast.Expr) and isinstance(doc.value, ast.Constant)}
    assert documented == {f.name for f in dataclasses.fields(st.Settings)}
    s = st.Settings()
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.alpha = 0.1
    assert s.to_json()["margin_se"] == s.margin_se and dataclasses.replace(s, alpha=0.01).alpha == 0.01
