"""Reproducible output files: gzip with a fixed header, so the same trip always gives the same bytes."""
import gzip
import io
import shutil
import zipfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np


@contextmanager
def open_binary(path: Path):
    """A binary output stream to `path`, gzip-compressed (no file name, mtime 0) when it ends in `.gz`."""
    path = Path(path)
    with open(path, "wb") as raw:
        if path.suffix == ".gz":
            with gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0, compresslevel=9) as z:
                yield z
        else:
            yield raw


def gzip_file(src: Path, dst: Path) -> None:
    """Compress `src` into `dst` as `open_binary` does."""
    with open(src, "rb") as fin, open_binary(dst) as fout:
        shutil.copyfileobj(fin, fout, 1 << 20)


def save_npz(path: Path, arrays: dict) -> None:
    """numpy's .npz layout (one .npy per array in a deflated zip), with fixed member dates so that reruns
    are byte-identical (np.savez_compressed stamps the current time)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for name, value in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asarray(value), allow_pickle=False)
            info = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            z.writestr(info, buf.getvalue())
