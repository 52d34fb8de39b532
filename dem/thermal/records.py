"""Model records: what the rest of the code needs to know about a thermal model.

Each model module declares, next to its law, one ``ModelRecord`` per model in a module-level
tuple ``RECORDS``. ``dem.thermal.registry`` collects the records of the modules it lists
(``registry.MODEL_MODULES``) and derives from them the name -> id tables, the aliases, the
required inputs and their defaults, the material and gas table layouts, the per-contact history
width and the neighbour reach; ``dem.thermal.dispatch`` generates the integer-switch dispatchers
(``direct_pp`` ...) from the records' ``laws``; ``dem.thermal.docs`` writes the input tables of
docs/models.md. Nothing else lists model names.
"""
import math
from dataclasses import dataclass, field

MATERIAL = "material"
GAS = "gas"


@dataclass(frozen=True)
class Input:
    """One column of the material table (per body) or of the gas/global table.

    key: scene key ([[materials]] or [gas]); table: MATERIAL or GAS; unit: SI unit ("-" for
    none); default: value used when the key is absent (None: required by the models that use
    it, NaN in the table); bounds: allowed closed range (lo, hi); description: one line.
    """
    key: str
    table: str
    unit: str
    default: object = None
    bounds: tuple = (0.0, math.inf)
    description: str = ""


@dataclass(frozen=True)
class ModelRecord:
    """Everything the solver, the scene validator, ``dem check`` and the docs need about a model.

    name: canonical scene name; mechanism: "direct", "indirect", "convection", "radiation",
    "friction", "partition", "contact_radius" or "correction"; id: integer passed to the njit
    kernels (unique within the mechanism); aliases: other accepted scene names;
    material: material keys each body needs; gas: gas/global keys the model reads (each has a
    default or is required); new_inputs: ``Input`` declarations of table columns this model
    introduces (appended after the existing columns; their column indices are passed to the
    model's laws as trailing integer arguments by the generated dispatchers, in declaration
    order); history: floats stored per contact (e.g. contact age and impact velocity);
    reach: gas key whose value, in particle radii and plus ``reach_offset``, is how far beyond
    contact the model needs neighbours (None: contacts only); laws: dispatcher slot -> njit
    function with the slot's signature (see dem.thermal.dispatch.SLOTS; empty for the
    mechanisms whose switch is written by hand); law: the physical law (for the docs);
    reference: citation and equation; summary: one line for the docs tables.
    """
    name: str
    mechanism: str
    id: int
    aliases: tuple = ()
    material: tuple = ()
    gas: tuple = ()
    new_inputs: tuple = ()
    history: int = 0
    reach: object = None
    reach_offset: float = 0.0
    laws: dict = field(default_factory=dict, compare=False, hash=False)
    law: object = field(default=None, compare=False, hash=False)
    reference: str = ""
    summary: str = ""

    def inputs(self):
        """(material keys, gas keys) the model reads, including its new inputs."""
        mat = list(self.material) + [i.key for i in self.new_inputs if i.table == MATERIAL]
        gas = list(self.gas) + [i.key for i in self.new_inputs if i.table == GAS]
        return tuple(dict.fromkeys(mat)), tuple(dict.fromkeys(gas))
