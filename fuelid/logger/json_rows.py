"""JSON records of many rows at once, byte for byte what orjson writes for each row's dict.

A record is built as a byte matrix, one row per record: its fields side by side, each a zero-padded
(rows, width) byte matrix (or the same bytes for every row); the zero bytes are then squeezed out. JSON text
never holds a zero byte (orjson escapes control characters), so nothing else is removed.
"""
import numpy as np
import orjson

Field = bytes | np.ndarray
"""The same bytes in every row, or an (rows, width) uint8 matrix of zero-padded bytes."""


def text_matrix(texts: list[bytes]) -> np.ndarray:
    """The byte strings `texts` as an (n, width) zero-padded uint8 matrix."""
    if not texts:
        return np.zeros((0, 1), np.uint8)
    return np.array(texts).view(np.uint8).reshape(len(texts), -1)


def number_texts(values: list) -> np.ndarray:
    """orjson's text of each number (int, float or None) as an (n, width) zero-padded uint8 matrix."""
    if not values:
        return np.zeros((0, 1), np.uint8)
    return text_matrix(orjson.dumps(values)[1:-1].split(b","))


def texts_by_value(values: np.ndarray, cache: dict, text) -> np.ndarray:
    """Per element of `values` (integers with few distinct values) the bytes `text(value)` as an (n, width)
    zero-padded uint8 matrix; `cache` keeps the texts between calls."""
    distinct, inverse = np.unique(values, return_inverse=True)
    table = []
    for v in distinct.tolist():
        t = cache.get(v)
        if t is None:
            t = cache[v] = text(v)
        table.append(t)
    return text_matrix(table)[inverse.ravel()]


def records(fields: list[Field], n: int) -> tuple[bytes, np.ndarray]:
    """The `n` rows of `fields` side by side, zero bytes squeezed out: (all the records, one after another,
    and the offsets of each, n + 1 of them: record i is [offsets[i], offsets[i + 1]))."""
    merged: list[Field] = []
    for f in fields:  # neighbouring constant bytes as one
        if isinstance(f, bytes) and merged and isinstance(merged[-1], bytes):
            merged[-1] += f
        else:
            merged.append(f)
    widths = [len(f) if isinstance(f, bytes) else f.shape[1] for f in merged]
    matrix = np.empty((n, sum(widths)), np.uint8)
    at = 0
    for f, w in zip(merged, widths):
        matrix[:, at : at + w] = np.frombuffer(f, np.uint8) if isinstance(f, bytes) else f
        at += w
    keep = matrix != 0
    offsets = np.zeros(n + 1, np.int64)
    np.cumsum(keep.sum(axis=1), out=offsets[1:])
    return matrix[keep].tobytes(), offsets
