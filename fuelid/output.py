"""What every `--json` prints: strict JSON on stdout (NaN and inf as null, numpy values as plain numbers)."""
import json
import math
import sys


def json_safe(x):
    """NaN/inf → None, numpy scalars and arrays → Python numbers and lists (by their tolist(), so this module
    does not load numpy for the commands that print no arrays), keys → str."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if hasattr(x, "tolist"):  # numpy arrays and scalars
        return json_safe(x.tolist())
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    return x


def print_json(obj) -> None:
    """Print obj as indented strict JSON and a newline."""
    json.dump(json_safe(obj), sys.stdout, indent=2, allow_nan=False)
    print()
