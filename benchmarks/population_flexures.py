"""The population's acute-angle flexures, drawn and built, against the published counts.

    .venv/bin/python benchmarks/population_flexures.py [--seeds 0-499] [--workers 2] [--out F]

Draws each seed's patient (anatomy/population.py), solves and bends its course
(`resolve_population`: anatomy/course.py, then anatomy/tortuosity.py), counts the built
course's flexures by the rule of anatomy/morphology.py, and writes one CSV row per patient
(seed, sex, length, flexures drawn and built, wall seconds). Prints the drawn and built
counts' mean, SD and range, their count per metre, and the published figures beside them:
Khashab et al. 2009 (10.9 +- 2.4 in colons of 189.5 cm, n = 505) and Hanson et al. 2007
(9.6 in 167 cm, 11.9 in 210.8 cm); and the share of patients whose course made the drawn
count. Each patient takes 3-30 s (four placements at most).
"""

import argparse
import csv
import dataclasses
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np


def seeds_of(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        if "-" in part:
            lo, hi = part.split("-")
            out += list(range(int(lo), int(hi) + 1))
        else:
            out.append(int(part))
    return out


def one(seed: int) -> dict:
    from capsule_drake.anatomy import ColonParams
    from capsule_drake.anatomy.morphology import acute_flexures
    from capsule_drake.anatomy.params import Population
    from capsule_drake.anatomy.population import resolve_population, resolved_patient
    start = time.perf_counter()
    params = dataclasses.replace(ColonParams(seed=seed), source=Population())
    try:
        _, (s, points, _, _) = resolve_population(params)
    except ValueError as error:
        return {"seed": seed, "error": str(error)}
    patient = resolved_patient(params)
    return {"seed": seed, "sex": patient.sex, "length_cm": 100.0 * s[-1],
            "drawn": patient.flexures, "built": len(acute_flexures(s, points)),
            "seconds": time.perf_counter() - start, "error": ""}


def main(argv=None) -> int:
    from capsule_drake.anatomy.population import (FLEXURES_HANSON, FLEXURES_KHASHAB,
                                                  FLEXURES_PER_METRE, flexure_distribution)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0-499")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("population_flexures.csv"))
    args = parser.parse_args(argv)
    seeds = seeds_of(args.seeds)
    fields = ["seed", "sex", "length_cm", "drawn", "built", "seconds", "error"]
    rows = []
    with open(args.out, "w", newline="") as f, ProcessPoolExecutor(args.workers) as pool:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        for row in pool.map(one, seeds):
            writer.writerow(row)
            f.flush()
            rows.append(row)
    good = [r for r in rows if not r["error"]]
    drawn = np.array([r["drawn"] for r in good], dtype=float)
    built = np.array([r["built"] for r in good], dtype=float)
    length = np.array([r["length_cm"] for r in good]) / 100.0
    mean, sd, _ = flexure_distribution()
    print(f"{len(good)} of {len(rows)} patients built ({len(rows) - len(good)} could not be)")
    for name, values in (("drawn", drawn), ("built", built)):
        print(f"  {name}: {values.mean():.2f} +- {values.std(ddof=1):.2f} "
              f"({values.min():.0f}-{values.max():.0f}), "
              f"{np.mean(values / length):.2f} per metre")
    print(f"  built = drawn in {np.mean(built == drawn):.1%}; "
          f"|built - drawn| <= 1 in {np.mean(np.abs(built - drawn) <= 1):.1%}")
    print(f"  model: {mean:.2f} +- {sd:.2f} ({FLEXURES_PER_METRE:.2f} per metre of length)")
    k = FLEXURES_KHASHAB
    print(f"  Khashab 2009: {k[0]} +- {k[1]} in {k[2]} cm: {k[0] / k[2] * 100:.2f} per metre")
    for group, (count, cm) in FLEXURES_HANSON.items():
        print(f"  Hanson 2007, {group}: {count} in {cm} cm: {count / cm * 100:.2f} per metre")
    seconds = np.array([r["seconds"] for r in good])
    print(f"  wall time per patient: median {np.median(seconds):.1f} s, "
          f"max {seconds.max():.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
