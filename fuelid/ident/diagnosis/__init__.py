"""The diagnosis loop: compare a model with measurements, see where it fails, learn which physical effect is
missing (ident.effects), and verify it by refitting.

The package follows the loop, each module using only those before it:

    statistics      the score tests, the AR whitener, Holm (plain arrays)
    run             the model run the diagnosis tests (ident.modelrun) and its gradients
    failures        where the model fails: whiteness, worst stretches, error map
    verification    the linearised refit scored on held-out blocks
    carryover       a generic bus signal's effect left out of each trip in turn, refitted by PEM
    delay           the fuel-signal delay, tested and verified on seed 2's reference model
    explanation     the sentence and the size of an effect
    candidate       Candidate, a candidate effect as a typed record, and what its tests found
    entries         how an effect enters the model (additive, scales the fuel, a torque, a shift): its columns, tests
                    and verification, one class per kind
    builds          the models `fuelid identify` would build on the data, built once each (ahead, in a worker), and the
                    check of what is recommended on them
    ranking         the candidates' tests, Holm, and a candidate's verification
    recommendation  when a candidate is confirmed, named and recommended, and the sentences that say why not
    selection       forward selection of every effect missing, re-testing the rest on the model refitted
    verdict         the engine map term, then the hidden effects, checked on the builds: `diagnose` → Diagnosis
"""
from fuelid.ident.diagnosis.candidate import Candidate, confirmed_effects
from fuelid.ident.diagnosis.ranking import rank_candidates
from fuelid.ident.diagnosis.run import Run, run_gradients
from fuelid.ident.diagnosis.verdict import Diagnosis, diagnose

__all__ = ["Candidate", "Diagnosis", "Run", "confirmed_effects", "diagnose", "rank_candidates", "run_gradients"]
