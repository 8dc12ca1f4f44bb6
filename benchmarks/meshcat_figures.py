"""The documentation's Meshcat figures (docs/), drawn by headless Chromium (needs `chromium`
on PATH).

    .venv/bin/python benchmarks/meshcat_figures.py [--out docs] [--only replay,arm,...]

- replay.png: recording.html of 20 s of the WithSensors drag (the capsule
  camera's frames and the run's plots beside the replay), at its end;
- arm_meshcat.png: recording.html of a short WithArm run, at its end;
- ex_vivo_meshcat.png: recording.html of a short ExVivoSegment run, at its end;
- fluid_meshcat.png: recording.html of a short Navigation run in population patient 1003
  with its lumen's state (residual fluid in the rectum, a narrowed sigmoid), at its end;
- teleop_browser.png: the live page of a browser-operator Teleop station after 1 s (the
  camera-view panel with the detected lumen in the scene).

Each run is simulated here (a few seconds each); prints what it wrote.
"""

import argparse
import dataclasses
import tempfile
from pathlib import Path

import cv2
from pydrake.geometry import Meshcat, MeshcatParams
from pydrake.systems.analysis import Simulator

from capsule_drake.io.headless import HeadlessPage, chromium_executable
from capsule_drake.app.run import simulate
from capsule_drake.scenario import load_scenario
from capsule_drake.station import make_station

# name -> (scenario, override, simulated seconds): the figures drawn from a run's replay.
REPLAYS = {
    "replay": ("WithSensors", None, 20.0),
    "arm_meshcat": ("WithArm", None, 3.0),
    "ex_vivo_meshcat": ("ExVivoSegment", None, 3.0),
    "fluid_meshcat": ("Navigation", "{colon: {seed: 1003, source: !Population {}, lumen: {}}}",
                      4.0),
}
SHOW_END = """new Promise(function (done) {
  const a = viewer.animator, t = a.duration - 1e-3;
  a.pause(); a.seek(t); a.display_progress(t); viewer.set_dirty();
  requestAnimationFrame(function () { requestAnimationFrame(function () { done(true); }); });
})"""


def replay_figure(name: str, exe: str, work: Path):
    scenario, override, duration = REPLAYS[name]
    scenario = dataclasses.replace(load_scenario(name=scenario, override=override),
                                   duration=duration)
    simulate(scenario, meshcat=Meshcat(MeshcatParams(port=0)), out_dir=work / name,
             progress=False)
    with HeadlessPage(exe, (work / name / "recording.html").as_uri(),
                      profile=work / f"{name}-chromium", timeout=60.0) as page:
        page.wait_for("typeof viewer !== 'undefined' && viewer.animator.duration > 0")
        page.evaluate(SHOW_END)
        return page.settled_screenshot(quiet=1.0, interval=0.25)


def teleop_figure(exe: str, work: Path):
    meshcat = Meshcat(MeshcatParams(port=0))
    scenario = load_scenario(name="Teleop", override=(
        "{epm: {mount: !Stage {}, driver: !Teleop {operator: browser}}}"))
    simulator = Simulator(make_station(scenario, meshcat))
    simulator.set_target_realtime_rate(0.0)
    simulator.AdvanceTo(1.0)
    with HeadlessPage(exe, meshcat.web_url(), profile=work / "teleop-chromium") as page:
        return page.settled_screenshot()


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs"))
    parser.add_argument("--only", default=None,
                        help="comma-separated figure names (default: all)")
    args = parser.parse_args()
    names = list(REPLAYS) + ["teleop_browser"]
    wanted = names if args.only is None else [n.strip() for n in args.only.split(",")]
    unknown = [n for n in wanted if n not in names]
    if unknown:
        parser.error(f"--only: unknown figure(s) {', '.join(unknown)} (known: {', '.join(names)})")
    exe = chromium_executable()
    if exe is None:
        parser.error("chromium is not on PATH")
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as work:
        for name in wanted:
            image = (teleop_figure(exe, Path(work)) if name == "teleop_browser"
                     else replay_figure(name, exe, Path(work)))
            path = args.out / f"{name}.png"
            cv2.imwrite(str(path), image)
            print(f"wrote {path}")


if __name__ == "__main__":
    main()
