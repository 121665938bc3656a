"""The models `fuelid identify --effects-from` would build on the diagnosed data (ident.identify.identify_model),
each built once — ahead, in a worker process beside the diagnosis, when it has one — and the check of what the
diagnosis recommends on them (`BuiltCheck`).

The diagnosis checks what it recommends on the model identify builds with it (selection, 5), and on a real engine
those builds are most of its time (PEM from two starts, 70–80 parameters). It can tell early which it may need — the
model with the engine's map term once that term's test rejects, the one with each effect forward selection accepts —
and `ModelBuilds.ask` hands such a build to the worker; the worker builds it while the diagnosis goes on testing
and verifying, and `ModelBuilds.model` takes it when the diagnosis needs it. The two processes share their PEM fits
(ident.identify.FitMemo): each sends every fit it makes to the other, and each takes the other's before it makes one.
So a fit is made once where the two need the same — forward selection's warm-started refit is the start of the build
with its effect (the build continues it), and the build's own fit from that start, kept on its way at the refit's
iteration limit (`checkpoints`), is that refit when the worker gets there first. A model never asked for is built in
the worker too when the worker built one with its leading effects (whose fits it is built through), else here,
beside whatever the worker is doing. The worker skips an effect its own builds show will not be added (the
model built with it failed, or simulates the data worse than the one without: the test the diagnosis's `BuiltCheck.add`
makes) and builds the model without it instead, which the diagnosis then asks for; if the diagnosis asks for the one
skipped after all, it is built here. identify_model is deterministic and the worker runs the same code on the same
kernels on one BLAS thread (fuelid.blas), so a model built there is the one built here, to the bit: the diagnosis is
the same with a worker or without (`workers=0`, the fleet's jobs, which run one per core already). A build asked for
in vain costs the worker's time only; the worker is stopped, whatever it is doing, on `close`.

The worker is forked (multiprocessing's "fork") when the first build is asked for: it starts with the data and the
fits made so far as this process's pages, nothing pickled, and this process copies only the pages it writes
afterwards; the fits made after go through the queues (a model and its search: tens of kilobytes). (Python 3.12 and
later warn when a process with threads forks, OpenBLAS's among them; the worker takes no lock those threads hold.)
"""
from __future__ import annotations

import collections
import multiprocessing
import pickle
import queue
import signal

import numpy as np

from fuelid.blas import one_blas_thread
from fuelid.errors import FuelidError
from fuelid.ident.diagnosis.candidate import Candidate
from fuelid.ident.identify import FitMemo, identify_model
from fuelid.ident.polymodel import PolyModel, Structure

_CONTEXT = multiprocessing.get_context("fork")
POLL_S = 0.5  # [s] how often a wait for the worker checks that it is still running


class WorkerLost(RuntimeError):
    """The worker process ended without building what it was asked for (killed, out of memory)."""


class Skipped(RuntimeError):
    """The worker built a model without an effect its builds show will not be added instead (`likely_added`)."""


class ModelBuilds:
    """The models identify_model builds on dataset ds from `structure` (speed and torque inputs; the effects add
    theirs) plus given effects ("ID" or "ID=VALUE"; defined: the engineer's, ident.effectfile), with base the model of
    `structure` without them (its second start), fits shared through one FitMemo (`memo`, with the worker's when there
    is one; checkpoints: its `FitMemo.checkpoints`, and the worker's). workers: 1 to build those asked for ahead in a
    worker process, 0 to build each here when taken. Use as a context manager, or `close`."""

    def __init__(self, ds, structure: Structure, defined=(), base: PolyModel | None = None, workers: int = 0,
                 checkpoints=()):
        if workers not in (0, 1):
            raise ValueError(f"workers must be 0 or 1, got {workers}")
        self.ds, self.structure, self.defined, self.base = ds, structure, tuple(defined), base
        self.memo = FitMemo(checkpoints, incoming=self._incoming, outgoing=self._outgoing)
        self._done: dict[tuple[str, ...], PolyModel | Exception] = {}
        self._asked: set[tuple[str, ...]] = set()  # what the worker has built or is building
        self.ahead = bool(workers)  # whether builds asked for are built ahead in a worker process
        self._worker: _Worker | None = None  # started when first asked for a build: none where none is asked for

    def ask(self, effects) -> None:
        """Start building the model with `effects` in the worker, if there is one and it was not asked for yet."""
        key = tuple(effects)
        if self.ahead and key not in self._done and key not in self._asked:
            if self._worker is None:  # it starts with the fits made here so far; those made later are sent
                self._worker = _Worker(self.ds, self.structure, self.defined, self.base, self.memo.items(),
                                       self.memo.checkpoints)
            self._worker.submit(key)
            self._asked.add(key)

    def _incoming(self) -> list:
        """The fits the worker made since this was last called (`FitMemo.incoming`)."""
        return self._worker.fits() if self._worker is not None else []

    def _outgoing(self, fits) -> None:
        """Send the fits made here to the worker, if there is one (`FitMemo.outgoing`)."""
        if self._worker is not None:
            self._worker.share(fits)

    def model(self, effects) -> PolyModel:
        """The model with `effects`: the worker's when asked for, or when the worker built a model with its leading
        effects (whose fits it is built through); else built here, beside whatever the worker is building (and here
        whenever the worker was lost: WorkerLost). Raises what identify_model raised (FuelidError,
        numpy.linalg.LinAlgError)."""
        key = tuple(effects)
        if key not in self._done:
            if any(key[:j] in self._asked for j in range(1, len(key))):
                self.ask(key)  # the worker fitted the stages it is built through (its leading effects): built there
            try:
                self._done[key] = self._from_worker(key) if key in self._asked else self.build(key)
            except (FuelidError, np.linalg.LinAlgError) as exc:  # raised again when asked again: it would be
                self._done[key] = exc
        if isinstance(self._done[key], Exception):
            raise self._done[key]
        return self._done[key]

    def _from_worker(self, key: tuple[str, ...]) -> PolyModel:
        try:
            return self._worker.result(key)
        except Skipped:
            return self.build(key)
        except WorkerLost:  # what it had built is lost with it: the rest is built here
            self.close()
            self._asked.clear()
            return self.build(key)

    def build(self, effects) -> PolyModel:
        """identify_model's model with `effects`, built here (`_built`)."""
        return _built(self.ds, self.structure, effects, self.defined, self.base, self.memo)

    def close(self) -> None:
        """Stop the worker, whatever it is building; builds asked for after are built here."""
        self.ahead = False
        if self._worker is not None:
            self._worker.stop()
            self._worker = None

    def __enter__(self) -> ModelBuilds:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _built(ds, structure: Structure, effects, defined, base: PolyModel | None, memo: FitMemo) -> PolyModel:
    """identify_model's model with `effects` on ds, on one BLAS thread (as in the diagnosis), fits through memo."""
    with one_blas_thread():
        return identify_model(ds, structure, list(effects), defined=defined, base=base, memo=memo)


class _Worker:
    """One forked process building models in the order asked (`_serve`), started with the fits `fits` (FitMemo
    items). Messages go both ways through queues whose feeder threads never block the sender: ("build", key) and
    ("fits", items) to the worker, ("built", (key, outcome)) and ("fits", items) back; outcomes come back in order."""

    def __init__(self, ds, structure: Structure, defined, base: PolyModel | None, fits, checkpoints):
        self._tasks, self._results = _CONTEXT.Queue(), _CONTEXT.Queue()
        self.process = _CONTEXT.Process(target=_serve, args=(self._tasks, self._results, ds, structure, defined, base,
                                                             fits, checkpoints), daemon=True)
        self.process.start()
        self._outcomes: dict[tuple[str, ...], tuple[bool, object]] = {}
        self._fits: list = []  # received, not yet taken (`fits`)

    def submit(self, key: tuple[str, ...]) -> None:
        self._tasks.put(("build", key))

    def share(self, fits) -> None:
        self._tasks.put(("fits", fits))

    def _take(self, message) -> None:
        kind, payload = message
        if kind == "fits":
            self._fits.extend(payload)
        else:
            done, outcome = payload
            self._outcomes[done] = outcome

    def fits(self) -> list:
        """The fits the worker sent since the last call (those already here: this never waits)."""
        for message in _waiting(self._results):
            self._take(message)
        fits, self._fits = self._fits, []
        return fits

    def result(self, key: tuple[str, ...]) -> PolyModel:
        """The model built for key (asked for by `submit`, or built instead of one asked for), or what its build
        raised; Skipped when the worker built another instead, WorkerLost if the process ended first."""
        while key not in self._outcomes:
            try:
                self._take(self._results.get(timeout=POLL_S))
            except queue.Empty:
                if not self.process.is_alive():
                    raise WorkerLost(f"the worker process ended (exit code {self.process.exitcode})") from None
        ok, value = self._outcomes.pop(key)
        if ok is None:
            raise Skipped(f"built {list(value)} instead of {list(key)}")
        if not ok:
            raise value
        return value

    def stop(self) -> None:
        # SIGKILL, not SIGTERM: a handler the process had when it was forked (a service's) could keep it alive
        self.process.kill()
        self.process.join()
        for q in (self._tasks, self._results):
            q.cancel_join_thread()  # what is left in them is dropped with the worker
            q.close()


def simulates_worse(rmse_with: float, rmse_without: float, min_gain_percent: float = 0.0) -> bool:
    """Whether the model built with an effect simulates the data worse than the one without it (RMS simulation
    errors, [output unit] both), or better by less than min_gain_percent [%] (0: no worse is enough): the effect is
    then not added (`BuiltCheck.add`)."""
    return rmse_with > (1 - min_gain_percent / 100) * rmse_without


def likely_added(effects: tuple[str, ...], rmse: dict) -> tuple[str, ...]:
    """effects without those that the models already built show will not be added (`BuiltCheck.add`): one whose
    model (with the effects kept before it) failed to build, or `simulates_worse` than the model without it when
    both were built. rmse: {effects: RMS simulation error [output unit] of the model built, None if it failed}."""
    kept: tuple[str, ...] = ()
    for e in effects:
        with_ = kept + (e,)
        if with_ in rmse and (rmse[with_] is None
                              or rmse.get(kept) is not None and simulates_worse(rmse[with_], rmse[kept])):
            continue
        kept = with_
    return kept


def _own_structure(model: PolyModel) -> Structure:
    """The orders of model's speed and torque inputs and noise model: the structure `fuelid identify` extends with
    the effects."""
    s = model.structure
    return Structure(nb=s.nb[:2], nf=s.nf[:2], nk=model.nk[:2], nc=s.nc, nd=s.nd, na=s.na)


def built_record(c: Candidate) -> dict:
    """Where c's `BuiltCheck` record goes: its refit record, or its verification for one forward selection did not
    refit (the fuel delay)."""
    return c.refit if c.refit is not None else c.verification


class BuiltCheck:
    """The model `fuelid identify --effects-from` builds on the diagnosed data from the effects recommended so far
    (ident.identify.identify_model: PEM from its own initialisation and from the effects added in turn, not from
    the model diagnosed), kept with its RMS simulation error [output unit] on those data: the diagnosis's
    built-model check (selection, 5)."""

    def __init__(self, model: PolyModel, ds, effects=(), workers: int = 0, checkpoints=()):
        self.specs, self.rmse = list(model.effects), None
        # its second start (identify_model) is the model diagnosed, when that is one; the model with E + [c] is built
        # through the fits of E's: fitted once
        self.builds = ModelBuilds(ds, _own_structure(model), effects, model if not model.effects else None, workers,
                                  checkpoints)
        self.memo = self.builds.memo
        self._expected: list[str] = []  # the effects expected to be added, in the order `add` will take them

    @property
    def ahead(self) -> bool:
        """Whether builds asked for ahead run in a worker process beside the diagnosis."""
        return self.builds.ahead

    def close(self) -> None:
        """Stop the builds' worker (`ModelBuilds.close`)."""
        self.builds.close()

    def expect(self, c: Candidate) -> None:
        """c is expected to be added after those expected before it: ask ahead for the model `add` will build with
        them (`_ask`)."""
        self._expected.append(c.spec)
        self._ask(self.specs + self._expected)

    def guess(self, c: Candidate) -> None:
        """Ask ahead for the model built with c after those expected, c not expected yet (a likely next one)."""
        self._ask(self.specs + self._expected + [c.spec])

    def _ask(self, specs: list[str]) -> None:
        """Ask ahead for the model with specs (`ModelBuilds.ask`), then (once) for the one without any effect
        added, which `add` compares the first added with: taken only at the end, it is built while the worker waits
        for forward selection to tell it the next (the diagnosis would otherwise build it then, itself)."""
        self.builds.ask(specs)
        self.builds.ask(self.specs)

    def _model(self, specs: list[str]) -> PolyModel:
        return self.builds.model(specs)

    def _rmse(self, specs: list[str]) -> float:
        return self._model(specs).validation["rmse"]["simulation"]

    def model_with(self, c: Candidate) -> PolyModel:
        """The model built with c added to the effects so far."""
        return self._model(self.specs + [c.spec])

    def rmse_with(self, c: Candidate) -> float:
        """RMS simulation error [output unit] of the model built with c added to the effects so far."""
        return self._rmse(self.specs + [c.spec])

    def add(self, c: Candidate, min_gain_percent: float = 0.0) -> bool:
        """Whether the model built with c added to the effects so far simulates the data no worse than the one
        without it — better by at least min_gain_percent [%] when that is given (`simulates_worse`);
        recorded as "built" (or its error) in c.refit, or in c.verification for one forward selection did not
        refit (the fuel delay), c added when so."""
        record = built_record(c)
        try:
            if self.rmse is None:
                self.rmse = self._rmse(self.specs)
            with_ = self.rmse_with(c)
        except (FuelidError, np.linalg.LinAlgError) as exc:
            record["built"] = {"effects": list(self.specs), "error": str(exc)}
            return False
        record["built"] = {"effects": list(self.specs), "rmse_without": self.rmse, "rmse_with": with_,
                           "min_gain_percent": min_gain_percent}
        if simulates_worse(with_, self.rmse, min_gain_percent):
            return False
        self.specs.append(c.spec)
        self.rmse = with_
        return True

    def given(self, c: Candidate) -> None:
        """Add c without checking it (the fuel delay where no engine term is added: its verification on the model
        as it is stands for the model identify builds)."""
        self.specs.append(c.spec)
        self.rmse = None


def _serve(tasks, results, ds, structure: Structure, defined, base: PolyModel | None, fits, checkpoints) -> None:
    """The worker: build each model asked for, in order, once — or, for one with an effect its builds show will not
    be added (`likely_added`), the model without it — and send it (or what its build raised) back; its fits go back as
    it makes them, and it takes the diagnosis's before it makes one (`_Worker`'s messages)."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # not the forking process's handler: a SIGTERM ends the worker
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the diagnosis's to handle; it stops the worker
    asked: collections.deque[tuple[str, ...]] = collections.deque()  # builds received, not yet made

    def take(message) -> list:
        """The fits of a message; a build asked for joins `asked`."""
        kind, payload = message
        if kind == "build":
            asked.append(payload)
            return []
        return payload

    def incoming() -> list:
        return [fit for message in _waiting(tasks) for fit in take(message)]

    memo = FitMemo(checkpoints, incoming=incoming, outgoing=lambda made: results.put(("fits", made)))
    memo.update(fits)
    rmse: dict[tuple[str, ...], float | None] = {}  # of each model built here [output unit]; None: its build failed
    while True:
        if not asked:
            memo.update(take(tasks.get()))
            continue
        key = asked.popleft()
        if key in rmse:  # built instead of another, and sent then
            continue
        likely = likely_added(key, rmse)
        if likely != key:
            results.put(("built", (key, (None, likely))))
            if likely in rmse:
                continue
        try:
            model = _built(ds, structure, likely, defined, base, memo)
            rmse[likely] = model.validation["rmse"]["simulation"]
            outcome = (True, model)
        except Exception as exc:  # noqa: BLE001 — raised in the diagnosis, where it is handled or is a bug
            rmse[likely] = None
            outcome = (False, exc if _picklable(exc) else RuntimeError(f"in the worker process: {exc!r}"))
        results.put(("built", (likely, outcome)))


def _waiting(q) -> list:
    """The messages already on queue q, in order (this never waits)."""
    messages = []
    while True:
        try:
            messages.append(q.get_nowait())
        except queue.Empty:
            return messages


def _picklable(exc: Exception) -> bool:
    """Whether exc survives the way back (an exception that does not would be lost on the queue's thread)."""
    try:
        pickle.loads(pickle.dumps(exc))
        return True
    except Exception:  # noqa: BLE001 — any failure to pickle or unpickle
        return False
