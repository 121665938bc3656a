"""The models `fuelid identify --effects-from` would build on the diagnosed data (ident.identify.identify_model),
each built once — ahead, in a worker process beside the diagnosis, when it has one.

The diagnosis checks what it recommends on the model identify builds with it (ranking, 5), and on a real engine
those builds are most of its time (PEM from two starts, 70–80 parameters). It can tell early which it may need —
the model with the engine's map term once that term's test rejects, the one with each effect forward selection
accepts — and `ModelBuilds.ask` hands such a build to the worker, with the fits made here since (forward selection's
warm-started refits, which the builds continue: ident.identify.FitMemo); the worker builds it while the diagnosis
goes on testing and verifying, and `ModelBuilds.model` takes it when the diagnosis needs it. A model never asked for
is built in the worker too when the worker built one with its leading effects (whose fits it is built through), else
here, beside whatever the worker is doing. identify_model is deterministic and the worker runs the same code on the
same kernels on one BLAS thread (fuelid.blas), so a model built there is the one built here, to the bit: the
diagnosis is the same with a worker or without (`workers=0`, the fleet's jobs, which run one per core already). A
build asked for in vain costs the worker's time only; the worker is stopped, whatever it is doing, on `close`.

The worker is forked (multiprocessing's "fork"): it starts with the data as this process's pages, nothing pickled,
and this process copies only the pages it writes afterwards. Python 3.12 and later warn when a process with threads
forks; the worker only builds models and exits.
"""
from __future__ import annotations

import multiprocessing
import multiprocessing.pool

import numpy as np

from fuelid.blas import one_blas_thread
from fuelid.errors import FuelidError
from fuelid.ident.identify import FitMemo, identify_model
from fuelid.ident.polymodel import PolyModel, Structure

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
        self._asked_ever: set[tuple[str, ...]] = set()  # what the worker has built or is building
        self._sent: set = set()  # the fits of `memo` the worker has too
        self._pool = _CONTEXT.Pool(1, _start_worker, (ds, structure, self.defined, base)) if workers else None

    @property
    def ahead(self) -> bool:
        """Whether there is a worker to build ahead in."""
        return self._pool is not None

    def ask(self, effects) -> None:
        """Start building the model with `effects` in the worker, if there is one and it was not asked for yet."""
        key = tuple(effects)
        if self._pool is not None and key not in self._done and key not in self._asked:
            fits = [(k, fit) for k, fit in self.memo.items() if k not in self._sent]  # e.g. the warm-started refits,
            self._sent.update(k for k, _ in fits)  # which the builds continue (ident.identify.FitMemo)
            self._asked[key] = self._pool.apply_async(_build_in_worker, (key, fits))
            self._asked_ever.add(key)

    def model(self, effects) -> PolyModel:
        """The model with `effects`: the worker's when asked for, or when the worker built a model with its leading
        effects (whose fits it is built through); else built here, beside whatever the worker is building. Raises
        what identify_model raised (FuelidError, numpy.linalg.LinAlgError)."""
        key = tuple(effects)
        if key not in self._done:
            if any(key[:j] in self._asked_ever for j in range(1, len(key))):
                self.ask(key)  # the worker fitted the stages it is built through (its leading effects): built there
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


def _build_in_worker(effects: tuple[str, ...], fits) -> PolyModel:
    _worker.memo.update(fits)
    return _worker.build(effects)
