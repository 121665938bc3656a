"""fuelid warmup: compile and cache the online estimators' numba kernels (ident.warmup), e.g. in an image build."""
import os

from fuelid.ident.warmup import compile_estimators
from fuelid.output import print_json


def add_arguments(p):
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def run(args) -> int:
    seconds = compile_estimators()
    where = os.environ.get("NUMBA_CACHE_DIR") or "__pycache__ beside fuelid/ident (or numba's user cache directory)"
    if args.json:
        print_json({"seconds": seconds, "cache": where})
    else:
        print(f"online estimators compiled and cached in {seconds:.1f} s ({where})")
    return 0
