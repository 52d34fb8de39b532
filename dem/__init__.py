"""thermodem: a Numba thermal DEM solver with an OpenFOAM coupling.

Public API::

    import dem
    sim = dem.Simulation.from_file("examples/settle_box.toml")
    sim.run(end_time=0.1)
    sim.state.position
"""
__version__ = "0.1.0"


def __getattr__(name):  # lazy: importing dem.thermal must not pull in the solver
    if name in ("Simulation",):
        from .simulation import Simulation
        return Simulation
    if name in ("SceneError",):
        from .scene import SceneError
        return SceneError
    raise AttributeError(name)
