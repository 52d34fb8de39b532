"""The coupled inputs: fluid data at each owned particle for the next steps of a coupled run,
written into the arrays declared for them in dem.schema (``when="fluid"``, ``"fluid_torque"``,
``"virtual_mass"``, and the thermal ``uf``/``tf``/``por``), which the compiled step reads like
any other state (docs/models.md, "Semi-implicit drag")."""


def set_fluid(world, stepper, force=None, velocity=None, temperature=None, porosity=None, drag=None, torque=None,
              torque_drag=None, added_mass=None):
    """See :meth:`dem.simulation.Simulation.set_fluid`."""
    st = world.state
    k = st.n_owned
    if force is not None:
        _explicit_and_implicit(st, "fluid", ("external_force", force), ("drag_beta", drag))
    if torque is not None:
        _explicit_and_implicit(st, "fluid_torque", ("external_torque", torque), ("rot_drag", torque_drag))
    if added_mass is not None:
        if not st.features.get("virtual_mass"):
            st.enable(virtual_mass=True)
        st.inv_mass_eff[:k] = 1.0 / (st.mass[:k] + added_mass)
        st.inv_mass_eff[k:] = st.inv_mass[k:]
    th = world.thermal
    if th is None:
        return
    if velocity is not None:
        st.uf[:k] = velocity
    if temperature is not None:
        st.tf[:k] = temperature
    if porosity is not None:
        st.por[:k] = porosity
        th.local_porosity = False
        from .thermal.heat import TI
        th.thi[TI.localpor] = 0  # the CFD void fraction is used instead
        stepper.forward_porosity()


def _explicit_and_implicit(st, feature, explicit, implicit):
    """Enable ``feature`` and set, on the owned rows, its explicit part (name, value) and its
    implicit coefficient (name, value, or None for 0); the ghost rows hold 0."""
    if not st.features.get(feature):
        st.enable(**{feature: True})
    k = st.n_owned
    for name, value in (explicit, implicit):
        a = getattr(st, name)
        a[:k] = 0.0 if value is None else value
        a[k:] = 0.0
