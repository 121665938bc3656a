"""What every `--json` prints: strict JSON on stdout (NaN and inf as null, numpy values as plain numbers)."""
import json
import math
import sys

import numpy as np


def json_safe(x):
    """NaN/inf → None, numpy scalars and arrays → Python numbers and lists, keys → str."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def print_json(obj) -> None:
    """Print obj as indented strict JSON and a newline."""
    json.dump(json_safe(obj), sys.stdout, indent=2, allow_nan=False)
    print()
