"""Which effects a fleet view names: those a model carries ("in the model") and the hidden effects its latest
diagnosis recommends and the model lacks ("missing"), each once. The engine's own map (its curvature, the
speed × torque product) is a property of the engine: never "missing", never an alert."""
from __future__ import annotations

ENGINE_PROPERTIES = frozenset({"engine_map", "power_nonlinearity"})


def effect_id(spec: str) -> str:
    """The id of an effect spec ("fuel_delay=0.36" → "fuel_delay")."""
    return spec.partition("=")[0].strip()


def in_model(effects) -> list[str]:
    """The ids of a model's effects, each once, in order."""
    return list(dict.fromkeys(effect_id(e) for e in effects))


def missing(candidates: list[dict], carried=()) -> list[str]:
    """The hidden effects a diagnosis (its JSON `candidates`, each with `id` or `effect`) recommends
    (`recommended: true`) that are neither carried by the model nor properties of the engine, each once, in the
    diagnosis's order."""
    have = set(in_model(carried)) | ENGINE_PROPERTIES
    ids = (effect_id(str(c.get("id") or c.get("effect") or "")) for c in candidates if c.get("recommended") is True)
    return [e for e in dict.fromkeys(ids) if e and e not in have]
