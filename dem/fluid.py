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
        if not st.features.get("fluid"):
            st.enable(fluid=True)
        st.external_force[:k] = force
        st.external_force[k:] = 0.0
        st.drag_beta[:k] = 0.0 if drag is None else drag
        st.drag_beta[k:] = 0.0
    if torque is not None:
        if not st.features.get("fluid_torque"):
            st.enable(fluid_torque=True)
        st.external_torque[:k] = torque
        st.external_torque[k:] = 0.0
        st.rot_drag[:k] = 0.0 if torque_drag is None else torque_drag
        st.rot_drag[k:] = 0.0
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
