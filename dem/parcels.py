"""The one test for 'this scene has parcels' (coarse graining, issue 15)."""
import numpy as np


def parcel_factors(sc):
    """The coarse-graining factor of each particle of scene ``sc``, or None when every one is 1:
    no parcels, and the run is exactly the one without the key."""
    cg = getattr(sc, "coarse_graining", None)
    return cg if cg is not None and np.any(cg != 1.0) else None
