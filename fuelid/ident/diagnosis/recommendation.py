"""When a candidate the tests found is confirmed, named and recommended, and what its explanation says when it is not:
the rules forward selection (ident.diagnosis.selection, 5) and the verdict (ident.diagnosis.verdict) share, over the
candidates' records (ident.diagnosis.candidate).

A candidate is `significant` — a missing effect the diagnosis names — when the Holm-corrected test rejects AND it
explains at least min_effect_percent (default 1 %) of the simulation error AND, when verified, the linearised refit
lowers the held-out RMS error by at least min_drop_percent (default 2 %) the way its physics says, identifiably and
never worse on a held-out trip, AND (after the first) forward selection accepts it given those before it. The
conjunction can only remove rejections, so the family-wise false-alarm rate of the first stays ≤ α. Significant
candidates are listed first, in the order accepted; then the rest by p-value. README gives the measured false alarms and
the table per hidden effect.

A significant candidate is `recommended` (what `fuelid identify --effects-from` adds) when it was verified, the model
re-identified with it simulates the data no worse than the model without it (or, for an effect with its physics, forward
selection's warm-started refit alone did not: selection, 5), and so does the model `fuelid identify` builds with it and
the effects recommended before it (selection, 5; better by min_drop_percent where the warm refit was worse) — and, for a
decoded bus signal in a generic form (level, rate, scales, torque, state of a signal fuelid has no physics for), only
when the data held several trips and it held up left out of each (leave-one-trip-out): in the linearised refit (4;
NOT_DETERMINED_BY_OTHER_TRIPS when no trip's fold determined it) and, once accepted, with its own dynamics and the model
re-identified by PEM on the other trips (diagnosis.carryover: its refit counts as not verified unless the pooled error
on the trips left out falls by min_drop_percent both ways). A signal engine speed and torque determine (a static map of
them leaves less than MIN_IDENTIFIABILITY² of its variance, `_why_inputs_determine`: EEC3's desired speed is the engine
speed but in neutral) is never added: whatever it explains is a function of speed and torque, the engine's own fuelling,
and other days cannot make it a hidden effect. On one trip any other such signal can stand in for whatever else moves
with the operating point that day (on a real engine its transient fuelling): named, with ONE_TRIP_ONLY, but not added. A
catalogued or engineer-defined effect brings its physics (sign, form) and is recommended from one trip. Forward
selection still re-identifies the model with such a signal when it accepts one (so that it explains away its twins and
what it stands in for), but what is recommended must have been verified on the model `fuelid identify --effects-from`
builds: an effect found given a signal that is not added is named, not recommended (`given_not_added`; one accepted that
way and added without it can make the model worse on another day: README) — unless an earlier round of forward selection
found and verified it given exactly the effects recommended before it (`found_given_added`: it was then confirmed on the
model identify builds with them, only not accepted first, a one-trip signal's drop being larger; on the map engine a
hidden inertia is so). A round given only some of them does not count: the others, absent there, may explain it away. So
once the search is built on a signal that is never added (`why_never_added`), every later round is given it and only a
candidate that may be added and was found in an earlier round given no such signal could still be recommended; with none
left, forward selection stops (`selection._nothing_left_to_recommend`). What is recommended is the same as with the
search run to its end; what would have been named after it, found given it, is not (on the map engine's DPF trip the
overrun cut-off and EEC1's demand torque after EEC3's desired speed).
"""
from __future__ import annotations

from fuelid.ident import effects as fx
from fuelid.ident.diagnosis.candidate import Candidate
from fuelid.ident.diagnosis.carryover import WAYS
from fuelid.ident.diagnosis.verification import MIN_IDENTIFIABILITY

GENERIC_WEIGHT = 0.8  # a generic bus signal must explain 25 % more than a named effect to be accepted first


def is_confirmed(c: Candidate, v: dict | None, min_drop_percent: float) -> bool:
    """Whether a verification v of c confirms it: the held-out RMS error falls by at least min_drop_percent (its
    entry kind's relevance), and the fuel moves the way the effect's physics says (Effect.sign: fuel cut on
    overrun falls, a regeneration adds fuel, the fuel signal lags), and its entry kind admits it (a fuel delay:
    entries.Shift.why_not_admitted). A candidate the refit did not or could not score stays as the tests found it."""
    if v is None or "error" in v:
        return True
    return c.entry.relevance(v) >= min_drop_percent and c.definition.sign * v["direction"] >= 0 \
        and v.get("identifiable", True) and not _worse_on_held_out_trips(v) \
        and c.entry.why_not_admitted(v, min_drop_percent) is None


def _worse_on_held_out_trips(v: dict) -> bool:
    """Whether adding the effect raises the RMS error over the trips, each left out of its refit (verification, 4;
    pooled over the trips: one trip's error can rise by a fraction of a % with noise while the others' fall)."""
    return "trips" in v and v["trips"]["pooled_rmse_drop_percent"] < 0


def refit_verified(c: Candidate) -> bool:
    """Whether the model re-identified with c simulates the data no worse than the model without it (forward
    selection's refit, 5; True for one not refitted: the fuel delay, verified on its reference model)."""
    return c.refit is None or c.refit["verified"]


def only_the_warm_refit_worse(c: Candidate) -> bool:
    """Whether a catalogued or engineer-defined c, verified on held-out data, was held back only because forward
    selection's warm-started refit simulated the data worse (selection, 5): that refit keeps the dynamics
    of the model without c and can end far from the minimum `fuelid identify` reaches from its own
    initialisation, so the model identify builds with c decides instead (`BuiltCheck`). A generic bus signal keeps
    its trip checks, which only a verified refit runs."""
    r = c.refit
    return r is not None and not r["verified"] and "error" not in r and not is_generic(c) \
        and c.verification is not None and "error" not in c.verification


def why_built_worse(b: dict) -> str:
    """What the explanation of a candidate the model identify builds does not take adds (b: its `BuiltCheck` record)."""
    after = f", after {', '.join(b['effects'])}" if b["effects"] else ""
    if "error" in b:
        return f" — but `fuelid identify` cannot build the model with it{after} ({b['error']}): not recommended"
    if b["min_gain_percent"] and b["rmse_with"] <= b["rmse_without"]:
        return f" — but forward selection's warm-started refit with it simulated these data worse, and the model " \
               f"`fuelid identify --effects-from` builds with it{after} (PEM from its own initialisation) lowers " \
               f"their RMS error by less than {b['min_gain_percent']:g} % ({b['rmse_without']:.3f} → " \
               f"{b['rmse_with']:.3f}): not recommended"
    return f" — but the model `fuelid identify --effects-from` builds with it{after} (PEM from its own " \
           f"initialisation) simulates these data worse (RMS error {b['rmse_without']:.3f} → " \
           f"{b['rmse_with']:.3f}): not recommended"


def why_refit_not_verified(c: Candidate) -> str:
    """What the explanation of a named candidate whose refit was not verified adds."""
    if "built" in c.refit:
        return why_built_worse(c.refit["built"])
    if "error" in c.refit:
        return f" — but the model cannot be re-identified with it ({c.refit['error']}): not recommended"
    if "trips" in c.refit:
        t = c.refit["trips"]
        if "error" in t:
            return f" — but the model cannot be re-identified with it leaving a trip out ({t['error']}): " \
                   "not recommended"
        short = [f"{way.words}, RMS error {t[name]['rmse_without']:.3f} → {t[name]['rmse_with']:.3f}"
                 for name, way in WAYS.items() if name in t and not t[name]["lowered"]]
        return f" — but fitted on the other trips it does not lower the error on the trips left out by " \
               f"{t['min_drop_percent']:g} % ({'; '.join(short)}, pooled, leave-one-trip-out by PEM): not recommended"
    return f" — but the model re-identified with it (PEM, from the model without it) simulates these data worse " \
           f"(RMS error {c.refit['rmse_without']:.3f} → {c.refit['rmse_with']:.3f}): not recommended"


def why_not_confirmed(c: Candidate, min_drop_percent: float) -> str:
    """What the explanation of a verified but unconfirmed candidate adds."""
    v, drop = c.verification, c.entry.relevance(c.verification)
    if drop < min_drop_percent:
        return f" — but adding it changes the held-out RMS error by {-drop:+.1f} % (a fall of " \
               f"{min_drop_percent:g} % is needed): not confirmed"
    if c.definition.sign * v["direction"] < 0:
        return " — but the refit moves the fuel the other way than this effect would: not confirmed"
    if (why := c.entry.why_not_admitted(v, min_drop_percent)) is not None:
        return why
    if not v.get("identifiable", True):
        return f" — but it is not identifiable from these data: its signal's variation makes only " \
               f"{100 * v['identifiability']:.0f} % of its column beyond an offset and the initial states " \
               "(the signal hardly varies, or only with the trip's start or, a bus signal whose physics is not known, " \
               "as a slow drift over the trip); data that differ in it (other days, places) are " \
               "needed: not recommended"
    return f" — but fitted on the other trips it makes the held-out trips worse (RMS error " \
           f"{-v['trips']['pooled_rmse_drop_percent']:+.1f} %, leave-one-trip-out): not recommended"


NOT_RECOMMENDED = "; not recommended: "  # how the clauses below begin: the verdict says the drop before them


ONE_TRIP_ONLY = (NOT_RECOMMENDED + "a bus signal fuelid knows no physics for, found on one trip (diagnose it "
                 "with other days' files to see whether it carries over)")
"""Why a generic bus-signal candidate found on one trip is named but not recommended (module docstring)."""


NOT_DETERMINED_BY_OTHER_TRIPS = (NOT_RECOMMENDED + "a bus signal fuelid knows no physics for, whose effect no "
                                 "trip left out had determined by the others (its carry-over is untested: diagnose "
                                 "it with more days' files)")
"""Why a generic bus-signal candidate is named but not recommended when no leave-one-trip-out fit determined it."""


def _why_inputs_determine(c: Candidate, ds) -> str | None:
    """Why generic bus-signal candidate c is named but not recommended when the model's inputs determine its signal
    (less than MIN_IDENTIFIABILITY² of its variance beyond the static map of speed and torque, a variance inflation
    factor of 10, as for identifiability: `fx.share_beyond_inputs`); None when they do not."""
    signal = c.definition.signals[0]
    share = fx.share_beyond_inputs(ds, signal)
    if share >= MIN_IDENTIFIABILITY ** 2:
        return None
    return NOT_RECOMMENDED + f"engine speed and torque determine {signal} (a static map of them leaves " \
           f"{100 * share:.1f} % of its variance), so what it explains is the engine's own fuelling at its " \
           "operating point — the engine's term and the model's gains hold that — not a hidden effect"


def inputs_determine(c: Candidate, ds) -> bool:
    """Whether c is a generic bus-signal candidate whose signal engine speed and torque determine
    (`_why_inputs_determine`): never added, on any data."""
    return is_generic(c) and _why_inputs_determine(c, ds) is not None


def why_never_added(c: Candidate, ds, v: dict | None = None) -> str | None:
    """Why c, a generic bus-signal candidate, is never recommended whatever else is (module docstring): speed and
    torque determine its signal (`_why_inputs_determine`), it was verified on one trip (ONE_TRIP_ONLY), or no trip
    left out determined it (NOT_DETERMINED_BY_OTHER_TRIPS); None when none holds, when c has known physics, or when
    its verification v (default c's own) is missing (which then decides: not verified)."""
    if not is_generic(c):
        return None
    if (why := _why_inputs_determine(c, ds)) is not None:
        return why
    v = c.verification if v is None else v
    if v is None or "error" in v:
        return None
    if "trips" not in v:
        return ONE_TRIP_ONLY
    return None if any(v["trips"]["determined"]) else NOT_DETERMINED_BY_OTHER_TRIPS


def is_generic(c: Candidate) -> bool:
    """Whether c is a decoded bus signal in one of the generic forms (ids FORM:SIGNAL), not a catalogued or an
    engineer-defined effect with known physics."""
    return ":" in c.effect


def priority(c: Candidate, v: dict | None = None, estimated: float | None = None) -> float:
    """Order of acceptance: the held-out RMS error drop of its verification v (default c's own) when verified,
    else the estimated drop (default c's own); a generic bus signal's discounted by GENERIC_WEIGHT (a named
    physical effect is preferred to a bus signal that explains no more than it)."""
    v = c.verification if v is None else v
    drop = (c.estimated_drop_percent if estimated is None else estimated) if v is None or "error" in v \
        else c.entry.relevance(v)
    return drop * (GENERIC_WEIGHT if is_generic(c) else 1.0)


def rounds_found(c: Candidate) -> list[list[str]]:
    """The effects given which each round of forward selection that found c had re-identified the model."""
    return (c.conditional or {}).get("found_given", [])


def not_recommended(c: Candidate, why: str) -> None:
    """c named but not recommended: its explanation's advice to add it replaced by `why` (a clause saying why)."""
    c.recommended = False
    c.explanation = c.explanation.replace(f"; add effect {c.spec}", "") + why


def accepted_given_not_added(c: Candidate, recommended: set[str]) -> list[str]:
    """The effects c was accepted given (its conditional record's) that are not among `recommended`."""
    return [e for e in (c.conditional or {}).get("given", []) if e not in recommended]


def given_not_added(c: Candidate, recommended: set[str]) -> list[str]:
    """The effects c was found and verified given that are not among `recommended`: those it was accepted given,
    none when a round of forward selection found it given recommended effects only (`found_given_added`)."""
    return [] if found_given_added(c, recommended) is not None else accepted_given_not_added(c, recommended)


def found_given_added(c: Candidate, recommended: set[str]) -> list[str] | None:
    """The effects given which a round of forward selection found c (significant, relevant, confirmed:
    `selection._retest`), the first such round whose effects are those recommended before c (`recommended`), no more and
    no fewer — so c was verified on the model `fuelid identify --effects-from` builds with them, though accepted in a
    later round given a bus signal that is not added (a one-trip signal with a larger drop accepted before it); None
    when no round was. (A round given only some of them verified c on a model without the others, which may explain it
    away.)"""
    return next((g for g in rounds_found(c) if set(g) == recommended), None)
