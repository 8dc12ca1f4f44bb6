"""The compliant wall's predictions beside published measurements (issue: tissue from what is
published). Nothing here is fitted to the figure it is set beside.

    python benchmarks/bench_tissue.py

(b) Burst pressure. A thin-walled tube of radius R and wall thickness h bursts when its hoop
    stress P R / h reaches the wall's ultimate tensile strength: P = sigma_u h / R (Laplace).
    With the wall's figures (h: 2.61 mm, EUS in vivo; sigma_u: 0.87 MPa, human rectum and
    sigmoid, Christensen 2015; 0.9 MPa, human large bowel across, Egorov 2002) and the
    model's lumen radii of the caecum and the sigmoid (the default patient's), beside cadaver
    colons insufflated to rupture: caecum 81 mmHg, sigmoid 169 mmHg ("Air-pressure-induced
    colon injury during diagnostic colonoscopy"). Also with the wall stretched to its failure
    strain before it bursts (62.8 % elongation, Christensen 2015: thinner by 1 / lambda and
    wider by lambda, P / lambda^2), a second reading of the same figures.
(c) Wall stiffness under a colonoscope's head. Johnson et al. 2019 pressed colonoscope heads
    perpendicular into porcine colon: 0.8 N/mm (small head) and 0.7 N/mm (large head,
    angled). The compliant wall's force on a hemispherical head of radius r_h pressed delta
    in is k pi delta^2 (3 r_h - delta) / 3 (the Winkler foundation's spherical cap); its
    secant stiffness F / delta, at depths of 2-6 mm (within the hemisphere), for the head
    radius of a 12-13 mm
    colonoscope (6.25 mm, U: the abstract gives no diameters) and the wall's foundation
    modulus at the nominal support and across the support's sweep (U).

Prints each check's simulated (or computed) figure, the published one, their ratio, and what
would have to change for them to meet.
"""

import math
import sys

from capsule_drake.anatomy import load_colon
from capsule_drake.physics.contact.compliant import (CompliantWall, foundation_modulus,
                                                      median_lumen_radius)
from capsule_drake.scenario import load_scenario

MMHG = 133.322
UTS = {"Christensen 2015, human rectum + sigmoid": 0.87e6,
       "Egorov 2002, human large bowel, across": 0.9e6}
FAILURE_STRETCH = 1.6281   # 62.81 % elongation at failure, human (Christensen 2015)
RUPTURE_MMHG = {"cecum": 81.0, "sigmoid": 169.0}
JOHNSON_N_PER_MM = {"small head, straight": 0.8, "large head, angled": 0.7}
HEAD_RADIUS = 0.00625      # m (U): a 12.5 mm colonoscope tip
SUPPORT_SWEEP = (0.0, 1.0e5, 3.0e5, 1.0e6, 3.0e6, 1.0e7)   # Pa/m (U)


def segment_radius(colon, name: str) -> float:
    """The mean lumen radius (m) over the middle half of a segment of the model's colon."""
    import numpy as np
    start, end = colon.centerline.segment_ranges()[name]
    s = np.linspace(start + 0.25 * (end - start), end - 0.25 * (end - start), 50)
    theta = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
    return float(np.mean(colon.wall_radius(s[:, None], theta[None, :])))


def burst_pressure(sigma_u: float, thickness: float, radius: float) -> float:
    """Laplace's burst pressure (Pa) of a thin-walled tube."""
    return sigma_u * thickness / radius


def head_force(k: float, depth: float, head_radius: float) -> float:
    """Force (N) of a Winkler foundation k (Pa/m) on a sphere pressed `depth` (at most its
    radius) into it."""
    return k * math.pi * depth**2 * (3.0 * head_radius - depth) / 3.0


def main() -> int:
    scenario = load_scenario()
    colon, _ = load_colon(scenario.colon)
    wall = CompliantWall()
    print("(b) burst pressure, Laplace P = sigma_u h / R, beside cadaver colons insufflated to "
          "rupture")
    print("| segment | R (mm) | strength | P (mmHg) | stretched to failure (mmHg) | measured "
          "(mmHg) | ratio | ratio stretched |")
    print("|---|---|---|---|---|---|---|---|")
    for segment, measured in RUPTURE_MMHG.items():
        radius = segment_radius(colon, segment)
        for source, sigma in UTS.items():
            p = burst_pressure(sigma, wall.thickness, radius) / MMHG
            stretched = p / FAILURE_STRETCH**2
            print(f"| {segment} | {radius * 1000:.1f} | {sigma / 1e6:.2f} MPa ({source}) | "
                  f"{p:.0f} | {stretched:.0f} | {measured:.0f} | {p / measured:.2f} | "
                  f"{stretched / measured:.2f} |")
    print("To meet at the caecum with these strengths the wall would be thinner at rupture or "
          "the lumen wider than the model's: h / R smaller by the ratio.\n")

    radius = median_lumen_radius(colon)
    print(f"(c) wall stiffness under a colonoscope's head (r_h = {HEAD_RADIUS * 1000:.2f} mm, U), "
          f"secant F / delta, the colon's median lumen radius {radius * 1000:.1f} mm")
    print("| support (Pa/m) | k (Pa/m) | F/d at 2 mm | 4 mm | 6 mm (N/mm) | measured (N/mm) | "
          "ratio at 4 mm |")
    print("|---|---|---|---|---|---|---|")
    for support in SUPPORT_SWEEP:
        k = foundation_modulus(CompliantWall(support_stiffness=support), radius)
        secants = [head_force(k, d, HEAD_RADIUS) / (d * 1000) for d in (0.002, 0.004, 0.006)]
        nominal = " (nominal)" if support == wall.support_stiffness else ""
        measured = JOHNSON_N_PER_MM["small head, straight"]
        print(f"| {support:.0e}{nominal} | {k:.2e} | {secants[0]:.3f} | {secants[1]:.3f} | "
              f"{secants[2]:.3f} | {measured} | {secants[1] / measured:.2f} |")
    print("Johnson's samples' support is not in the abstract: a sample on a rigid plate is held "
          "by its thickness alone (E / h = "
          f"{wall.through_thickness_modulus / wall.thickness:.1e} Pa/m), far stiffer.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
