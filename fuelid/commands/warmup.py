"""fuelid warmup: compile and cache the online estimators' numba kernels (ident.warmup), e.g. in an image build, and
say whether the install built the offline fits' compiled filter (ident.filters)."""
import os

from fuelid.ident.filters import compiled
from fuelid.ident.warmup import compile_estimators
from fuelid.output import print_json


def add_arguments(p):
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def run(args) -> int:
    seconds = compile_estimators()
    where = os.environ.get("NUMBA_CACHE_DIR") or "__pycache__ beside fuelid/ident (or numba's user cache directory)"
    filter_compiled = compiled()
    if args.json:
        print_json({"seconds": seconds, "cache": where, "compiled_filter": filter_compiled})
    else:
        print(f"online estimators compiled and cached in {seconds:.1f} s ({where})")
        print("offline fits' filter: compiled (fuelid/ident/_iir.c)" if filter_compiled else
              "offline fits' filter: not compiled (the install found no C compiler: gcc and python3-dev on Debian); "
              "identify and diagnose use scipy's loop, slower, with the same results")
    return 0
