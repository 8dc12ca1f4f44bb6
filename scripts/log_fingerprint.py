"""Fingerprints of the named scenarios' runs, to show a refactoring changed no behaviour.

    python scripts/log_fingerprint.py OUT [--duration S] [--scenarios A,B]
    python scripts/log_fingerprint.py --compare OUT_BEFORE OUT_AFTER

The first form runs every named scenario of diagrams/default.yaml (or those given) for
`--duration` simulated seconds (default 2) and writes, per scenario, its `logs.npz`,
`metrics.json` and `station.txt` (the diagram's systems and exported ports, in order) under
OUT/<scenario>/. The second compares two such folders: each logged array bit for bit, and
where it differs, its largest absolute difference; the station's systems and ports; the
metrics. Exits 1 when a log differs by more than 1e-9.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

TOLERANCE = 1e-9
WALL_CLOCK_METRICS = {"real_time_factor", "wall_time_s", "wall_time"}


def station_listing(station) -> str:
    lines = [f"system {s.get_name()} {type(s).__name__}" for s in station.GetSystems()]
    lines += [f"output {station.get_output_port(i).get_name()}"
              for i in range(station.num_output_ports())]
    lines += [f"input {station.get_input_port(i).get_name()}"
              for i in range(station.num_input_ports())]
    return "\n".join(lines) + "\n"


def record(out: Path, duration: float, names: list[str] | None) -> None:
    from capsule_drake.app.run import close_render_worker, simulate
    from capsule_drake.scenario import DEFAULT_SCENARIO_FILE, load_scenario, scenario_names
    from capsule_drake.station import make_station

    for name in names or scenario_names(DEFAULT_SCENARIO_FILE):
        scenario = load_scenario(name=name, override=f"duration: {duration}")
        folder = out / name
        station = make_station(scenario)
        (folder).mkdir(parents=True, exist_ok=True)
        (folder / "station.txt").write_text(station_listing(station))
        close_render_worker(station)
        del station
        result = simulate(scenario, out_dir=folder, progress=False)
        print(f"{name}: {result.status}", flush=True)


def compare(before: Path, after: Path) -> int:
    worst = 0.0
    for folder in sorted(p for p in before.iterdir() if p.is_dir()):
        other = after / folder.name
        if not other.is_dir():
            print(f"{folder.name}: missing in {after}")
            worst = np.inf
            continue
        a, b = np.load(folder / "logs.npz"), np.load(other / "logs.npz")
        notes = []
        if set(a.files) != set(b.files):
            notes.append(f"arrays differ: {sorted(set(a.files) ^ set(b.files))}")
            worst = np.inf
        for key in sorted(set(a.files) & set(b.files)):
            x, y = a[key], b[key]
            if x.shape != y.shape:
                notes.append(f"{key}: shape {x.shape} != {y.shape}")
                worst = np.inf
            elif x.dtype.kind in "fiu" and not np.array_equal(x, y, equal_nan=True):
                d = float(np.nanmax(np.abs(x.astype(float) - y.astype(float))))
                notes.append(f"{key}: max |diff| {d:.3g}")
                worst = max(worst, d)
            elif x.dtype.kind not in "fiu" and not np.array_equal(x, y):
                notes.append(f"{key}: differs")
                worst = np.inf
        lines_a = (folder / "station.txt").read_text().splitlines()
        lines_b = (other / "station.txt").read_text().splitlines()
        systems_a = [x for x in lines_a if x.startswith("system ")]
        systems_b = [x for x in lines_b if x.startswith("system ")]
        ports_a = [x for x in lines_a if not x.startswith("system ")]
        ports_b = [x for x in lines_b if not x.startswith("system ")]
        if systems_a != systems_b:
            notes.append("the station's systems differ" if sorted(systems_a) != sorted(systems_b)
                         else "the station's systems are the same, in another order")
        if ports_a != ports_b:
            notes.append("the station's ports differ" if sorted(ports_a) != sorted(ports_b)
                         else "the station's ports are the same, in another order")
        ma = json.loads((folder / "metrics.json").read_text())
        mb = json.loads((other / "metrics.json").read_text())
        changed = sorted(k for k in set(ma) | set(mb) if ma.get(k) != mb.get(k)
                         and k not in WALL_CLOCK_METRICS)
        if changed:
            notes.append(f"metrics differ: {', '.join(changed)}")
        print(f"{folder.name}: {'; '.join(notes) if notes else 'bit-identical'}")
    print(f"largest log difference: {worst:.3g}")
    return 0 if worst <= TOLERANCE else 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", nargs="?", type=Path)
    parser.add_argument("--duration", type=float, default=2.0)
    parser.add_argument("--scenarios", default=None)
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("BEFORE", "AFTER"))
    args = parser.parse_args()
    if args.compare:
        return compare(*args.compare)
    if args.out is None:
        parser.error("give OUT, or --compare BEFORE AFTER")
    record(args.out, args.duration, args.scenarios.split(",") if args.scenarios else None)
    return 0


if __name__ == "__main__":
    sys.exit(main())
