"""A picture of a built station: each system a box with the ports that are wired or exported,
each wire an arrow from an output to the inputs it feeds (the documentation's diagram page).

Drawn from the built diagram itself (`Diagram.connection_map`, its exported ports' locators,
and the systems each block added), so it shows what `make_station` built, not a sketch.
Columns follow the signal flow: the plant and scene graph first, then each system one column
after the last system it reads; the wires that close the loop into the plant run back under
the boxes. Matplotlib only (Graphviz is not a Python package and not on a fresh machine).

    python -m capsule_drake.app.diagram_picture OUT.svg [SCENARIO]
"""

from __future__ import annotations

import argparse
import dataclasses
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyBboxPatch  # noqa: E402
from matplotlib.path import Path as PlotPath  # noqa: E402
from matplotlib.patches import PathPatch  # noqa: E402
from pydrake.systems.framework import InputPortIndex, OutputPortIndex  # noqa: E402

from capsule_drake.scenario import load_scenario  # noqa: E402
from capsule_drake.station import make_station  # noqa: E402


FONT = 7.0                       # points
CHAR = 0.60 * FONT / 72.0        # inches per character of the monospace font
ROW = 0.16                       # inches per port row
HEAD = 0.38                      # inches of a box's title rows
GAP_X, GAP_Y = 0.9, 0.30         # inches between columns, between boxes
PALETTE = ("#d8ecf3", "#f6e3c7", "#dcefd8", "#efd9ef", "#f3f1c9", "#e4e0f4", "#f7d8d8",
           "#d9f0ee", "#ececec")


@dataclasses.dataclass
class Box:
    name: str
    block: str
    kind: str
    inputs: list[str]
    outputs: list[str]
    column: int = 0
    x: float = 0.0
    y: float = 0.0                # top edge (inches, y down)

    @property
    def width(self) -> float:
        left = max((len(p) for p in self.inputs), default=0)
        right = max((len(p) for p in self.outputs), default=0)
        title = max(len(self.name), len(self.block) + len(self.kind) + 3)
        return max(title, left + right + 3) * CHAR + 0.2

    @property
    def height(self) -> float:
        return HEAD + ROW * max(len(self.inputs), len(self.outputs), 1) + 0.08

    def port_y(self, k: int) -> float:
        return self.y + HEAD + ROW * (k + 0.5)


@dataclasses.dataclass
class StationGraph:
    boxes: dict[str, Box]
    wires: list[tuple[str, str, str, str]]      # (from box, output, to box, input)
    exported: dict[tuple[str, str], str]        # (box, port) -> the station's port name


def _class_name(system) -> str:
    """The system's class, pydrake's template instances written as Drake's C++ does
    (`MultibodyPlant_𝓣float𝓤` -> `MultibodyPlant<float>`)."""
    return re.sub("_\N{MATHEMATICAL BOLD SCRIPT CAPITAL T}(.*?)\N{MATHEMATICAL BOLD SCRIPT CAPITAL U}",
                  r"<\1>", type(system).__name__)


def station_graph(station, systems_of: dict[str, list[str]]) -> StationGraph:
    """The boxes, wires and exported names of a built station (`systems_of`: the systems
    each block added, as make_station fills it)."""
    block_of = {name: block for block, names in systems_of.items() for name in names}
    wires = []
    used_in, used_out = {}, {}
    for (to_system, to_index), (from_system, from_index) in station.connection_map().items():
        out = from_system.get_output_port(from_index).get_name()
        inp = to_system.get_input_port(to_index).get_name()
        wires.append((from_system.get_name(), out, to_system.get_name(), inp))
        used_out.setdefault(from_system.get_name(), set()).add(out)
        used_in.setdefault(to_system.get_name(), set()).add(inp)
    exported = {}
    for k in range(station.num_output_ports()):
        system, index = station.get_output_port_locator(OutputPortIndex(k))
        port = system.get_output_port(index).get_name()
        exported[(system.get_name(), port)] = station.get_output_port(k).get_name()
        used_out.setdefault(system.get_name(), set()).add(port)
    for k in range(station.num_input_ports()):
        for system, index in station.GetInputPortLocators(InputPortIndex(k)):
            port = system.get_input_port(index).get_name()
            exported[(system.get_name(), port)] = station.get_input_port(k).get_name()
            used_in.setdefault(system.get_name(), set()).add(port)
    boxes = {}
    for system in station.GetSystems():
        name = system.get_name()
        ins = [system.get_input_port(i).get_name() for i in range(system.num_input_ports())]
        outs = [system.get_output_port(i).get_name() for i in range(system.num_output_ports())]
        boxes[name] = Box(name, block_of.get(name, "(the run's)"), _class_name(system),
                          [p for p in ins if p in used_in.get(name, ())],
                          [p for p in outs if p in used_out.get(name, ())])
    return StationGraph(boxes, wires, exported)


def _layout(graph: StationGraph) -> None:
    """Columns by the longest chain of wires from the plant (wires into the plant and the
    scene graph close the loop and are not counted); boxes in a column ordered by where
    what they read sits (two sweeps of the barycentre rule)."""
    roots = {"plant", "scene_graph"}
    forward = [(a, b) for a, _, b, _ in graph.wires if b not in roots and a != b]
    column = {name: 0 for name in graph.boxes}
    for _ in range(len(graph.boxes)):
        changed = False
        for a, b in forward:
            if column[b] < column[a] + 1 and column[a] + 1 < len(graph.boxes):
                column[b] = column[a] + 1
                changed = True
        if not changed:
            break
    # The plant and the scene graph alone in the first column (the loop's wires reach them
    # from below); a system that reads nothing sits just before its first reader.
    reads = {b for _, b in forward}
    for name in graph.boxes:
        if name in roots:
            column[name] = 0
        elif name in reads:
            column[name] += 1
    readers = {}
    for a, b in forward:
        readers.setdefault(a, []).append(column[b])
    for name in graph.boxes:
        if name not in roots and name not in reads:
            column[name] = max(1, min(readers.get(name, [2])) - 1)
    columns: dict[int, list[str]] = {}
    for name in sorted(graph.boxes, key=lambda n: (n not in roots, n != "plant", n)):
        columns.setdefault(column[name], []).append(name)
    order = {name: float(k) for names in columns.values() for k, name in enumerate(names)}
    for _ in range(2):
        for c in sorted(columns)[1:]:
            def centre(name):
                feeds = [order[a] for a, b in forward if b == name and column[a] < c]
                return sum(feeds) / len(feeds) if feeds else order[name]
            columns[c].sort(key=centre)
            for k, name in enumerate(columns[c]):
                order[name] = float(k)
    x = 0.2
    for c in sorted(columns):
        width = max(graph.boxes[n].width for n in columns[c])
        y = 0.2
        for name in columns[c]:
            box = graph.boxes[name]
            box.column, box.x, box.y = c, x + (width - box.width) / 2, y
            y += box.height + GAP_Y
        x += width + GAP_X


def draw(graph: StationGraph, path: Path, title: str = "") -> Path:
    """Draws the station to `path` (SVG or PNG, by its suffix)."""
    _layout(graph)
    boxes = graph.boxes.values()
    label = {box: max((len(n) for (b, _), n in graph.exported.items() if b == box), default=0)
             for box in graph.boxes}
    width = max(b.x + b.width + label[b.name] * CHAR * 0.8 for b in boxes) + 0.3
    low = max(b.y + b.height for b in boxes)
    back = [w for w in graph.wires if graph.boxes[w[2]].column <= graph.boxes[w[0]].column]
    height = low + 0.25 + 0.07 * len(back) + 0.5
    fig = plt.figure(figsize=(width, height))
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(0, width)
    ax.set_ylim(height, 0)
    ax.axis("off")
    blocks = sorted({b.block for b in boxes})
    colour = {block: PALETTE[k % len(PALETTE)] for k, block in enumerate(blocks)}
    text = dict(fontsize=FONT, family="monospace", va="center", parse_math=False)
    for b in boxes:
        ax.add_patch(FancyBboxPatch((b.x, b.y), b.width, b.height, linewidth=0.8,
                                    boxstyle="round,pad=0.0,rounding_size=0.05",
                                    facecolor=colour[b.block], edgecolor="#555555"))
        ax.text(b.x + 0.08, b.y + 0.12, b.name, fontweight="bold", **text)
        ax.text(b.x + 0.08, b.y + 0.27, f"{b.block}: {b.kind}", color="#555555", **text)
        for k, port in enumerate(b.inputs):
            ax.text(b.x + 0.08, b.port_y(k), port, ha="left", **text)
        for k, port in enumerate(b.outputs):
            ax.text(b.x + b.width - 0.08, b.port_y(k), port, ha="right", **text)
            name = graph.exported.get((b.name, port))
            if name is not None:
                ax.text(b.x + b.width + 0.04, b.port_y(k) - 0.05, name, ha="left",
                        color="#00707a", fontsize=FONT - 1.5, family="monospace", parse_math=False)
        for k, port in enumerate(b.inputs):
            name = graph.exported.get((b.name, port))
            if name is not None:
                ax.text(b.x - 0.04, b.port_y(k) - 0.05, name, ha="right", color="#00707a",
                        fontsize=FONT - 1.5, family="monospace")
    lane = low + 0.25
    for a, out, b, inp in graph.wires:
        source, target = graph.boxes[a], graph.boxes[b]
        x0, y0 = source.x + source.width, source.port_y(source.outputs.index(out))
        x1, y1 = target.x, target.port_y(target.inputs.index(inp))
        if target.column > source.column:
            mid = (x0 + x1) / 2
            vertices = [(x0, y0), (mid, y0), (mid, y1), (x1, y1)]
            codes = [PlotPath.MOVETO, PlotPath.CURVE4, PlotPath.CURVE4, PlotPath.CURVE4]
            style = dict(edgecolor="#333333", linewidth=0.6)
        else:
            vertices = [(x0, y0), (x0 + 0.15, y0), (x0 + 0.15, lane), (x1 - 0.15, lane),
                        (x1 - 0.15, y1), (x1, y1)]
            codes = [PlotPath.MOVETO] + [PlotPath.LINETO] * 5
            style = dict(edgecolor="#b04040", linewidth=0.6)
            lane += 0.07
        ax.add_patch(PathPatch(PlotPath(vertices, codes), facecolor="none", **style))
        ax.annotate("", xy=(x1, y1), xytext=(x1 - 0.1, y1),
                    arrowprops=dict(arrowstyle="-|>", color=style["edgecolor"], lw=0.6))
    if title:
        ax.text(0.2, height - 0.22, title, fontsize=FONT + 1, va="center")
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


def draw_scenario(path: Path, scenario_name: str = "WithSensors") -> StationGraph:
    """Builds the named scenario's station and draws it to `path`."""
    systems_of: dict = {}
    station = make_station(load_scenario(name=scenario_name), systems_of=systems_of)
    graph = station_graph(station, systems_of)
    draw(graph, path, f"The station of scenario {scenario_name}: every system, the ports "
                      "wired or exported (teal: the station's port names), wires into the "
                      "plant (red) close the loop")
    return graph


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("scenario", nargs="?", default="WithSensors")
    args = parser.parse_args(argv)
    graph = draw_scenario(args.out, args.scenario)
    print(f"{args.out}: {len(graph.boxes)} systems, {len(graph.wires)} wires, "
          f"{len(graph.exported)} exported ports")


if __name__ == "__main__":
    main()
