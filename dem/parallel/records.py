"""Contact history keyed by global ids, independent of rank and row order.

The step keeps contact history in slots aligned with the neighbour list (fast, local).
To move history between ranks (migration), or into a checkpoint that another number of
ranks reads, each active slot becomes a record (id_lo, id_hi, spring, rolling spring, age)
oriented from the lower to the higher id; after a list is built, every slot looks its
pair up by key and takes the record back with the orientation of its row.
"""
import numpy as np

FIELDS = ("a", "b", "hist", "rhist", "age")


def extract(ids, nb, nnb, hist, rhist, age):
    """Records of every slot holding history (a contact, or a rolling spring/age)."""
    S = nb.shape[1]
    rows = nnb.shape[0]
    valid = np.arange(S)[None, :] < nnb[:, None]
    act = np.any(hist[:rows] != 0.0, axis=2)
    rolling = rhist.shape[0] > 0
    has_age = age.shape[0] > 0
    if rolling:
        act |= np.any(rhist[:rows] != 0.0, axis=2)
    if has_age:
        act |= age[:rows, :, 0] != 0.0
    i, s = np.nonzero(valid & act)
    j = nb[i, s]
    gi = ids[i]
    gj = ids[j]
    sign = np.where(gi < gj, 1.0, -1.0)[:, None]
    return dict(a=np.minimum(gi, gj), b=np.maximum(gi, gj), hist=hist[i, s] * sign,
                rhist=rhist[i, s] * sign if rolling else None, age=age[i, s] if has_age else None)


def concat(parts):
    parts = [p for p in parts if p is not None]
    out = {}
    for k in FIELDS:
        vals = [p[k] for p in parts if p[k] is not None]
        out[k] = np.concatenate(vals) if vals else None
    return out


def subset(rec, mask):
    return {k: (None if rec[k] is None else rec[k][mask]) for k in FIELDS}


def involving(rec, ids):
    """Records of pairs that involve any of ``ids``."""
    return subset(rec, np.isin(rec["a"], ids) | np.isin(rec["b"], ids))


def restore(rec, ids, nb, nnb, hist, rhist, age, key_base):
    """Fill the history slots of a freshly built list from the records."""
    if rec is None or rec["a"].size == 0:
        return 0
    S = nb.shape[1]
    valid = np.arange(S)[None, :] < nnb[:, None]
    i, s = np.nonzero(valid)
    j = nb[i, s]
    gi = ids[i]
    gj = ids[j]
    key = np.minimum(gi, gj) * key_base + np.maximum(gi, gj)
    rkey = rec["a"] * key_base + rec["b"]
    order = np.argsort(rkey, kind="stable")
    rk = rkey[order]
    pos = np.searchsorted(rk, key)
    posc = np.minimum(pos, rk.size - 1)
    found = (pos < rk.size) & (rk[posc] == key)
    src = order[posc[found]]
    i, s = i[found], s[found]
    sign = np.where(gi[found] < gj[found], 1.0, -1.0)[:, None]
    hist[i, s] = rec["hist"][src] * sign
    if rhist.shape[0] and rec["rhist"] is not None:
        rhist[i, s] = rec["rhist"][src] * sign
    if age.shape[0] and rec["age"] is not None:
        age[i, s] = rec["age"][src]
    return int(found.sum())
