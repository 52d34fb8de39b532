"""The one test for 'this scene has parcels' (coarse graining, issue 15)."""
import numpy as np


def parcel_factors(sc):
    """The coarse-graining factor of each particle of scene ``sc``, or None when every one is 1:
    no parcels, and the run is exactly the one without the key."""
    cg = getattr(sc, "coarse_graining", None)
    if cg is None:
        return None
    groups = getattr(sc, "group_cg", None)   # a scene set up per rank (MPI): its groups decide
    if getattr(sc, "distributed", False) and groups is not None:
        return cg if any(c != 1.0 for c in groups) else None
    return cg if np.any(cg != 1.0) else None
