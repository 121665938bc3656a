"""Progress bars that show on a terminal and stay quiet when piped."""
from tqdm import tqdm


def progress(iterable=None, *, total=None, desc=None, unit="it"):
    """tqdm with disable=None: drawn only when stderr is a terminal."""
    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=None, leave=False)
