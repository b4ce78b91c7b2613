"""Synthetic SeqSLAM routes shared by the SeqSLAM test modules."""

import numpy as np


def route(rng, n_ref, n_query, speed, dim=64, noise=1.5, integer=True):
    """Patch-normalised-like integer descriptors of a route; the query revisits it at ``speed``
    with noise. ``integer=False`` adds noise so no two trajectory sums tie (without
    enhancement integer sums tie often, and torch.topk, which ranks both modes' candidates,
    picks any of the tied ones at the K-th place)."""
    ref = 127 + np.clip(np.round(rng.normal(0, 2.5, (n_ref, dim))), -8, 8)
    pos = np.minimum(np.round(np.arange(n_query) * speed).astype(int), n_ref - 1)
    query = np.clip(ref[pos] + np.round(rng.normal(0, noise, (n_query, dim))), 119, 135)
    if not integer:
        ref, query = ref + rng.uniform(0, 0.5, ref.shape), query + rng.uniform(0, 0.5, query.shape)
    return ref, query
