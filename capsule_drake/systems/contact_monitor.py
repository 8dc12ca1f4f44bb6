"""ContactMonitor: how hard the capsule is pressed against the colon wall."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.plant import ContactResults
from pydrake.systems.framework import LeafSystem


class ContactMonitor(LeafSystem):
    """Sums the magnitudes of all contact forces in the plant's ContactResults.

    In this scene only the capsule touches anything (the EPM and table have no collision
    geometry), so the sum is the total load between capsule and wall.

    .. pydrake_system::

        name: ContactMonitor
        input_ports:
        - contact_results
        output_ports:
        - contact_load

    contact_load is a 1-vector in newtons: the sum over hydroelastic contact surfaces and
    point contacts of the magnitude of each one's resultant force.
    """

    def __init__(self):
        super().__init__()
        self._contact_results_port = self.DeclareAbstractInputPort(
            "contact_results", AbstractValue.Make(ContactResults()))
        self._contact_load_port = self.DeclareVectorOutputPort(
            "contact_load", 1, self._calc_contact_load)

    def _calc_contact_load(self, context, output):
        results = self._contact_results_port.Eval(context)
        total = 0.0
        for i in range(results.num_hydroelastic_contacts()):
            total += np.linalg.norm(
                results.hydroelastic_contact_info(i).F_Ac_W().translational())
        for i in range(results.num_point_pair_contacts()):
            total += np.linalg.norm(results.point_pair_contact_info(i).contact_force())
        output.SetAtIndex(0, total)
