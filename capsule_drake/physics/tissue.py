"""What the colon wall tolerates: contact pressures from the literature on mucosal injury,
and how long a run pressed the wall above them.

The contact's pressure is the hydroelastic pressure field's peak over the capsule's contact
surfaces (`physics/contact_monitor.py` `peak_contact_pressure`); point contact (the
"convex_pieces" model) has no pressure field and reports none. Sources and their status:
docs/sources.md, section 3.
"""

from __future__ import annotations

import numpy as np

INJURY_PRESSURE = 330e3
"""Pa. Acute compressive injury of human colon and small bowel: grasps of 100-600 kPa held
10 s on surgical specimens; serosal change significant at 500 and 600 kPa, and the fitted
safety threshold 329-330 kPa (BMJ Surgery, Interventions & Health Technologies 3:e000084,
2021). A press of seconds above it is a press a surgeon's grasper is not allowed."""

ISCHAEMIA_PRESSURE = 30.0 * 133.322
"""Pa (30 mmHg, 4.0 kPa). Sustained pressure at which the bowel wall's blood flow falls:
intraluminal 30 mmHg cut intestinal flow at once in dogs (Boley et al., Am. J. Surg. 117,
1969) and mucosal flow of rabbit colon by 61-89 %. A bound for pressing minutes on one
place, not seconds."""

PRESSURE_THRESHOLDS = {"injury": INJURY_PRESSURE, "ischaemia": ISCHAEMIA_PRESSURE}


def time_above(times, values, threshold: float) -> float:
    """Seconds that a sampled signal spent above `threshold`: each sample held until the
    next (the last one for no time). NaN samples count as below."""
    times, values = np.asarray(times, dtype=float), np.asarray(values, dtype=float)
    if len(times) < 2:
        return 0.0
    with np.errstate(invalid="ignore"):
        above = values[:-1] > threshold
    return float(np.sum(np.diff(times)[above]))
