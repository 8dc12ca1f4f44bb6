"""Contact between the capsule and the colon wall: one model per module, chosen by the
scenario's `contact` (a tagged union, as epm.driver is).

    !RigidWall       the stand-in: a wall that does not yield, a stiff layer on the capsule,
                     Coulomb 0.2 (rigid.py); for comparison and for the speed runs
    !CompliantWall   the wall yields as a wall of measured thickness and moduli on an
                     elastic support, with the colon's measured friction (compliant.py)

Each model's module owns its wall's and capsule's contact geometry and properties, any force
it adds, and its parts of the run guard (`wall_allowance`, `wall_tears`) and of printed
figures (`label`); it registers itself as the "contact" block (blocks.py). What they share
is in common.py.
"""

from capsule_drake.physics.contact.compliant import CompliantWall
from capsule_drake.physics.contact.rigid import RigidWall

CONTACT_MODELS = (RigidWall, CompliantWall)
"""The members of the scenario's `contact` union, the first the default."""
