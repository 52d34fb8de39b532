"""Name -> integer id of the contact laws; the step kernel switches on these ids.

One compiled kernel with integer switches is cached once and serves every scene
(measured: a specialised kernel per scene recompiles for ~10 s per new combination,
the switch costs nothing measurable because the branch is perfectly predicted).
"""
CONTACT_MODELS = {"hertz_mindlin": 0, "linear_spring_dashpot": 1}
ROLLING_MODELS = {"none": 0, "constant_torque": 1, "epsd": 2}
# how the viscous damping coefficient is obtained from the restitution coefficient
DAMPING_MODELS = {"exact": 0, "tsuji_liggghts": 1}
# how the tangential spring follows the contact plane and is capped (dem.contact.tangential)
TANGENTIAL_MODELS = {"rescaled": 0, "projected": 1}
