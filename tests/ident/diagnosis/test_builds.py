"""ident.diagnosis.builds: the models `fuelid identify` would build, built once each, ahead in a worker process —
the same models, to the bit, as built here, the worker's errors raised here, and the worker stopped on close."""
import multiprocessing
import os
import signal

import numpy as np
import pytest

from fuelid.errors import FuelidError
from fuelid.ident.diagnosis.builds import ModelBuilds, likely_added, simulates_worse
from fuelid.ident.identify import identify_model, refit_with_effects
from tests.ident import hidden


@pytest.fixture(scope="module")
def ds():
    return hidden.make("dpf_regeneration", n=4000, seed=1)


def test_a_model_built_in_the_worker_is_the_one_identify_builds(ds):
    with ModelBuilds(ds, hidden.STRUCTURE, workers=1) as builds:
        builds.ask(["dpf_regeneration"])
        ahead = builds.model(["dpf_regeneration"])
        assert builds.model(["dpf_regeneration"]) is ahead and builds.memo.made == 0  # built once, in the worker
        # never asked for, but built through the fits of the one with the regeneration: in the worker too
        after = builds.model(["dpf_regeneration", "inertia"])
        assert builds.memo.made == 0
        # never asked for, and nothing to build it through: built here, of the fit the worker made as the others'
        # start (the model without effects), which it sent
        here = builds.model([])
        assert builds.memo.made == 0 and len(builds.memo) > 0
    for built, effects in ((ahead, ["dpf_regeneration"]), (after, ["dpf_regeneration", "inertia"]), (here, [])):
        expected = identify_model(ds, hidden.STRUCTURE, effects)
        assert np.array_equal(built.theta, expected.theta)
        assert built.validation == expected.validation and built.effects == expected.effects


def test_the_diagnosis_and_its_worker_make_each_fit_once(ds):
    """Forward selection's warm-started refit (here 3 iterations) is the start of the worker's build with its effect,
    which continues it; and the worker's own fit from that start, kept on its way at the refit's limit
    (checkpoints), is the refit asked for here after it. The same models, to the bit, as made apart."""
    base = identify_model(ds, hidden.STRUCTURE)
    with ModelBuilds(ds, hidden.STRUCTURE, base=base, workers=1, checkpoints=(3,)) as builds:
        warm = refit_with_effects(base, ds, ["dpf_regeneration"], max_iter=3, memo=builds.memo)
        assert builds.memo.made == 1
        builds.ask(["dpf_regeneration"])  # the worker continues the refit
        built = builds.model(["dpf_regeneration"])
        builds.ask(["inertia"])
        builds.model(["inertia"])
        # the worker's fit from this refit's start, kept at 3 iterations or stopped before
        again = refit_with_effects(base, ds, ["inertia"], max_iter=3, memo=builds.memo)
        assert builds.memo.made == 1
    assert warm.info["stop_reason"] == "max_iterations"  # so the worker's build went on from it
    expected = identify_model(ds, hidden.STRUCTURE, ["dpf_regeneration"], base=base)
    assert np.array_equal(built.theta, expected.theta) and built.info["starts"] == expected.info["starts"]
    assert np.array_equal(again.theta, refit_with_effects(base, ds, ["inertia"], max_iter=3).theta)


def test_without_a_worker_each_model_is_built_when_taken(ds):
    builds = ModelBuilds(ds, hidden.STRUCTURE)
    builds.ask(["dpf_regeneration"])  # nothing to build ahead in
    assert not builds.ahead and len(builds.memo) == 0
    model = builds.model(["dpf_regeneration"])
    assert np.array_equal(model.theta, identify_model(ds, hidden.STRUCTURE, ["dpf_regeneration"]).theta)
    builds.close()


def test_what_the_worker_cannot_build_is_raised_here_each_time_it_is_asked_for(ds):
    with ModelBuilds(ds, hidden.STRUCTURE, workers=1) as builds:
        builds.ask(["no_such_effect"])
        for _ in range(2):
            with pytest.raises(FuelidError, match="no_such_effect"):
                builds.model(["no_such_effect"])


def test_a_lost_worker_costs_its_builds_not_the_answer(ds):
    """A worker killed while building (out of memory, say): what was asked of it is built here, and the rest too."""
    with ModelBuilds(ds, hidden.STRUCTURE, workers=1) as builds:
        builds.ask(["dpf_regeneration"])
        os.kill(builds._worker.process.pid, signal.SIGKILL)
        model = builds.model(["dpf_regeneration"])
        assert not builds.ahead and len(builds.memo) > 0  # built here
    assert np.array_equal(model.theta, identify_model(ds, hidden.STRUCTURE, ["dpf_regeneration"]).theta)


def test_closing_stops_the_worker_whatever_it_is_building(ds):
    builds = ModelBuilds(ds, hidden.STRUCTURE, workers=1)
    assert multiprocessing.active_children() == []  # started when first asked for a build
    builds.ask(["dpf_regeneration"])
    assert len(multiprocessing.active_children()) == 1
    builds.close()
    assert not builds.ahead and multiprocessing.active_children() == []
    builds.close()  # closing twice is harmless


def test_the_worker_stops_whatever_signal_handlers_this_process_has(ds):
    """A service that handles SIGTERM itself (to shut down cleanly) forks the worker with that handler: closing must
    still stop it, and not wait for it for ever."""
    previous = signal.signal(signal.SIGTERM, lambda *_: None)
    try:
        builds = ModelBuilds(ds, hidden.STRUCTURE, workers=1)
        builds.ask(["dpf_regeneration"])
        builds.model(["dpf_regeneration"])  # the worker is now idle, waiting for the next build
        builds.close()
        assert multiprocessing.active_children() == []
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_an_effect_is_likely_added_unless_the_models_built_show_it_simulates_worse():
    rmse = {("map",): 1.0, ("map", "delay"): 1.2, ("map", "inertia"): 0.9, ("fan",): None}  # [L/h]; None: failed
    assert likely_added(("map", "delay", "inertia"), rmse) == ("map", "inertia")
    assert likely_added(("map", "inertia", "delay"), rmse) == ("map", "inertia", "delay")  # not built: no evidence
    assert likely_added(("map", "fan"), rmse) == ("map", "fan")
    assert likely_added(("fan", "map"), rmse) == ("map",)  # the build with the fan failed: not added
    assert likely_added(("map", "ambient"), {**rmse, ("map", "ambient"): None}) == ("map",)
    assert likely_added(("map", "delay"), {**rmse, ("map", "delay"): 1.0}) == ("map", "delay")  # no worse: added


def test_a_model_built_with_an_effect_simulates_worse_unless_it_gains_what_is_asked():
    """RMS simulation errors [L/h] with and without the effect: no worse is enough, unless a gain is asked for."""
    assert not simulates_worse(1.0, 1.0) and simulates_worse(1.001, 1.0)
    assert simulates_worse(0.99, 1.0, min_gain_percent=2) and not simulates_worse(0.97, 1.0, min_gain_percent=2)


def test_the_worker_builds_the_model_without_an_effect_that_simulates_worse_instead(ds):
    """Asked for the model with the regeneration, a fuel delay these data do not have, and the inertia: once its own
    builds show the delay simulates the data worse, the worker builds the one without it — what the diagnosis will
    ask for (`BuiltCheck.add`) — and a model it skipped is built here, the same."""
    spurious = "fuel_delay=0.4"
    with ModelBuilds(ds, hidden.STRUCTURE, workers=1) as builds:
        for effects in (["dpf_regeneration"], ["dpf_regeneration", spurious],
                        ["dpf_regeneration", spurious, "inertia"]):
            builds.ask(effects)
        rmse = [builds.model(e).validation["rmse"]["simulation"] for e in (["dpf_regeneration"],
                                                                          ["dpf_regeneration", spurious])]
        assert rmse[1] > rmse[0]  # the data this test needs
        instead = builds.model(["dpf_regeneration", "inertia"])
        assert len(builds.memo) == 0  # built in the worker, unasked
        skipped = builds.model(["dpf_regeneration", spurious, "inertia"])
        assert len(builds.memo) > 0  # built here
    for built, effects in ((instead, ["dpf_regeneration", "inertia"]),
                           (skipped, ["dpf_regeneration", spurious, "inertia"])):
        assert np.array_equal(built.theta, identify_model(ds, hidden.STRUCTURE, effects).theta)


def test_one_worker_or_none():
    with pytest.raises(ValueError, match="workers"):
        ModelBuilds(None, hidden.STRUCTURE, workers=2)
