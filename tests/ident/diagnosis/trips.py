"""Synthetic trips joined into one dataset, as several recordings (days) are."""
import dataclasses

import numpy as np


def joined(*trips, gap_s: float = 3600.0):
    """The datasets one after another, each starting gap_s [s] after the previous one's end."""
    t, offset = [], 0.0
    for ds in trips:
        t.append(ds.t - ds.t[0] + offset)
        offset = t[-1][-1] + gap_s
    first = trips[0]
    return dataclasses.replace(
        first, t=np.concatenate(t), u=np.vstack([d.u for d in trips]), y=np.concatenate([d.y for d in trips]),
        valid=np.concatenate([d.valid for d in trips]),
        cycle=np.concatenate([d.cycle + 1000 * k for k, d in enumerate(trips)]),
        extra={k: np.concatenate([d.extra[k] for d in trips]) for k in first.extra})
