"""Contact history keyed by global ids, independent of rank and row order.

The step keeps contact history in slots aligned with the neighbour list (fast, local).
To move history between ranks (migration), or into a checkpoint that another number of
ranks reads, each active slot becomes a record (id_lo, id_hi, spring, rolling spring, age)
oriented from the lower to the higher id; after a list is built, every slot looks its
pair up by key and takes the record back with the orientation of its row.
"""
import numpy as np

from .. import schema as S

# the history arrays declared with a record in dem.schema, and their parity
HISTORY = tuple(f for f in S.FIELDS if f.owner == "pair" and f.record)
FIELDS = ("a", "b") + tuple(f.name for f in HISTORY)


def extract(st):
    """Records of every slot holding history (a contact, or a rolling spring/age) of the
    state ``st`` (dem.state.State)."""
    nb, nnb = st.nb, st.nnb
    S_ = nb.shape[1]
    rows = nnb.shape[0]
    valid = np.arange(S_)[None, :] < nnb[:, None]
    act = np.zeros(valid.shape, bool)
    present = [f for f in HISTORY if getattr(st, f.name).shape[0]]
    for f in present:
        a = getattr(st, f.name)[:rows]
        act |= (a[:, :, 0] != 0.0) if f.record == "even" else np.any(a != 0.0, axis=2)
    i, s = np.nonzero(valid & act)
    j = nb[i, s]
    gi = st.id[i]
    gj = st.id[j]
    sign = np.where(gi < gj, 1.0, -1.0)[:, None]
    out = dict(a=np.minimum(gi, gj), b=np.maximum(gi, gj))
    for f in HISTORY:
        a = getattr(st, f.name)
        out[f.name] = None if f not in present else (a[i, s] * sign if f.record == "odd" else a[i, s])
    return out


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


def restore(rec, st, key_base):
    """Fill the history slots of a freshly built list of the state ``st`` from the records."""
    if rec is None or rec["a"].size == 0:
        return 0
    nb, nnb, ids = st.nb, st.nnb, st.id
    # every id of the list and of the records below the base (particles created during the run
    # have ids above the set-up's largest)
    key_base = max(int(key_base), int(ids.max(initial=0)) + 1, int(rec["b"].max(initial=0)) + 1)
    S_ = nb.shape[1]
    valid = np.arange(S_)[None, :] < nnb[:, None]
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
    for f in HISTORY:
        a = getattr(st, f.name)
        if a.shape[0] and rec.get(f.name) is not None:
            a[i, s] = rec[f.name][src] * sign if f.record == "odd" else rec[f.name][src]
    return int(found.sum())
