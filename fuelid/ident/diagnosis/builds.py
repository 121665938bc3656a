"""The models `fuelid identify --effects-from` would build on the diagnosed data (ident.identify.identify_model),
each built once — ahead, in a worker process beside the diagnosis, when it is given one.

The diagnosis checks what it recommends on the model identify builds with it (ranking, 5), and on a real engine
those builds are most of its time (PEM from two starts of a model of 70–80 parameters). It can tell early which it
may need: the model with the engine's map term once that term's test rejects, the one with each effect forward
selection accepts once the refit with it is verified. `ModelBuilds.ask` hands such a build to the worker, which runs
it while the diagnosis goes on testing and verifying; `ModelBuilds.model` takes it when the diagnosis needs it (and
builds it here if it was never asked for). identify_model is deterministic and the worker runs the same code on the
same kernels (it imports fuelid first, fuelid.blas) on one BLAS thread, so a model built there is the one built
here, to the bit: the diagnosis is the same with a worker or without (`workers=0`, what the fleet's jobs use: one job
per core already). A build asked for in vain costs the worker's time only; the worker is stopped, whatever it is
doing, when the diagnosis closes its builds.
"""
from __future__ import annotations

import multiprocessing
import multiprocessing.pool

import numpy as np

from fuelid.blas import one_blas_thread
from fuelid.errors import FuelidError
from fuelid.ident.identify import FitMemo, identify_model
from fuelid.ident.polymodel import PolyModel, Structure

# A worker is forked from a server process that imported fuelid before numpy (fuelid.blas), never from the
# diagnosing process itself: after a fork every page that process writes and the child shares is copied first.
_CONTEXT = multiprocessing.get_context("fork")

_worker: ModelBuilds | None = None  # the worker process's own builds (`_start_worker`)


class ModelBuilds:
    """The models identify_model builds on dataset ds from `structure` (speed and torque inputs; the effects add
    theirs) plus given effects ("ID" or "ID=VALUE"; defined: the engineer's, ident.effectfile), with base the model of
    `structure` without them (its second start), fits shared through one FitMemo (`memo`). workers: 1 to build those
    asked for ahead in a worker process, 0 to build each here when taken. Use as a context manager, or `close`."""

    def __init__(self, ds, structure: Structure, defined=(), base: PolyModel | None = None, workers: int = 0):
        if workers not in (0, 1):
            raise ValueError(f"workers must be 0 or 1, got {workers}")
        self.ds, self.structure, self.defined, self.base = ds, structure, tuple(defined), base
        self.memo = FitMemo()
        self._done: dict[tuple[str, ...], PolyModel | Exception] = {}
        self._asked: dict[tuple[str, ...], multiprocessing.pool.AsyncResult] = {}
        self._pool = _CONTEXT.Pool(1, _start_worker, (ds, structure, self.defined, base)) if workers else None

    @property
    def ahead(self) -> bool:
        """Whether there is a worker to build ahead in."""
        return self._pool is not None

    def ask(self, effects) -> None:
        """Start building the model with `effects` in the worker, if there is one and it was not asked for yet."""
        key = tuple(effects)
        if self._pool is not None and key not in self._done and key not in self._asked:
            self._asked[key] = self._pool.apply_async(_build_in_worker, (key,))

    def model(self, effects) -> PolyModel:
        """The model with `effects`: the worker's when asked for, else built here. Raises what identify_model
        raised (FuelidError, numpy.linalg.LinAlgError)."""
        key = tuple(effects)
        if key not in self._done:
            self.ask(key)  # built in the worker, asked for or not: its memo holds the fits of the builds before
            asked = self._asked.pop(key, None)
            try:
                self._done[key] = asked.get() if asked is not None else self.build(key)
            except (FuelidError, np.linalg.LinAlgError) as exc:  # raised again when asked again: it would be
                self._done[key] = exc
        if isinstance(self._done[key], Exception):
            raise self._done[key]
        return self._done[key]

    def build(self, effects) -> PolyModel:
        """identify_model's model with `effects`, built here (on one BLAS thread, as in the diagnosis)."""
        with one_blas_thread():
            return identify_model(self.ds, self.structure, list(effects), defined=self.defined, base=self.base,
                                  memo=self.memo)

    def close(self) -> None:
        """Stop the worker, whatever it is building."""
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()
            self._pool = None

    def __enter__(self) -> ModelBuilds:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _start_worker(ds, structure: Structure, defined, base: PolyModel | None) -> None:
    global _worker
    _worker = ModelBuilds(ds, structure, defined, base)


def _build_in_worker(effects: tuple[str, ...]) -> PolyModel:
    return _worker.build(effects)
