"""The diagnosis: where a model fails on measurements, which physical effect it is missing, and whether adding it
helps on data the fit did not see (docs/explanation/diagnosis.md).

The package follows the method, each module using only those before it:

    settings     every threshold with its meaning (Settings)
    statistics   the score tests, the AR whitener, Holm (plain arrays)
    run          the model run the screening tests (ident.modelrun) and its gradients
    failures     where the model fails: whiteness, worst stretches, error map
    size         a recommended effect's size in the model built with it (its fuel contribution)
    candidate    the typed decisions: Status, Reason, MapStatus, the evidence, Candidate
    screening    each candidate's columns as it enters the model, its two tests, Holm over the family
    yardstick    folds of blocks or trips, the refits on each, the paired per-block held-out comparison
    selection    the engine map's status, then forward selection with the yardstick
    render       the explanations, the verdict and the JSON, from the typed decisions (Diagnosis)
    pipeline     `diagnose`: the stages in order
"""
from fuelid.ident.diagnosis.candidate import Candidate, MapStatus, Reason, Status, confirmed_effects, effects_to_add
from fuelid.ident.diagnosis.pipeline import diagnose
from fuelid.ident.diagnosis.render import Diagnosis
from fuelid.ident.diagnosis.selection import Progress
from fuelid.ident.diagnosis.settings import Settings

__all__ = ["Candidate", "Diagnosis", "MapStatus", "Progress", "Reason", "Settings", "Status", "confirmed_effects",
           "diagnose", "effects_to_add"]
