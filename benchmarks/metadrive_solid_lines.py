"""Solid lines that cut into the lanes of a MetaDrive route, per scenario, against the drive table.

    python benchmarks/metadrive_solid_lines.py --scenarios 0 200 --table benchmarks/results/drive_recipe.json \\
        --runs runs/drive --out benchmarks/results/metadrive_solid_lines.json

MetaDrive ends an episode as out of road when the car's body touches a solid (continuous) line
(``on_continuous_line_done``, on by default). This script loads each scenario's map (no car
driving, no traffic) and looks for solid-line segments (their physics bodies, the ones the car
collides with) that lie *inside* one of the lanes the navigation route runs along, deeper than
``--margin`` metres from the lane's edges: a line there cuts across a lane the car is meant to
drive in. A car (about 1.85 m wide) centred in its lane touches a line that reaches within 0.93
m of the lane's centre. The JSON lists, per scenario, each such line with the lane, where along
the lane it is and how close it comes to the centre, and the route roads on which every lane has
such a line; with ``--table`` (a JSON of ``benchmarks/drive_recipe.py`` on the same scenarios)
also the success of MetaDrive's expert, and with ``--runs`` (that script's run directories, whose
``seed_N/heldout.json`` hold each episode's result) of each seed, on the scenarios with and
without such lines. Not a test.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from drivelab.api import make_env
from provenance import provenance  # benchmarks/provenance.py

SOLID = ("ROAD_LINE_SOLID_SINGLE_WHITE", "ROAD_LINE_SOLID_SINGLE_YELLOW")
CAR_HALF_WIDTH = 0.93  # metres; MetaDrive's default car is ~1.85 m wide


def solid_segments(world) -> list[np.ndarray]:
    """Points along every solid-line body in the physics world: one (k, 2) array per segment."""
    segments = []
    for node in world.getGhosts():
        if node.getName() not in SOLID or node.getNumShapes() == 0:
            continue
        transform = node.getTransform()
        centre, heading = transform.getPos(), math.radians(transform.getHpr()[0])
        half_length = node.getShape(0).getHalfExtentsWithoutMargin()[0]
        along = np.linspace(-half_length, half_length, max(2, int(2 * half_length / 0.25) + 1))
        segments.append(np.stack([centre[0] + along * math.cos(heading), centre[1] + along * math.sin(heading)], axis=1))
    return segments


def route_roads(env) -> list[tuple[str, str, list]]:
    """Every road on the agent's navigation route: (start node, end node, its lanes)."""
    checkpoints = env.agent.navigation.checkpoints
    graph = env.current_map.road_network.graph
    return [(start, end, graph[start][end]) for start, end in zip(checkpoints[:-1], checkpoints[1:])]


def lines_in_lanes(env, margin: float) -> list[dict]:
    """Solid lines inside a route lane, deeper than ``margin`` from its edges."""
    found = []
    segments = solid_segments(env.engine.physics_world.static_world)
    for lane in (lane for _, _, lanes in route_roads(env) for lane in lanes):
        for points in segments:
            coords = np.array([lane.local_coordinates(p) for p in points])
            inside = (coords[:, 0] > 0) & (coords[:, 0] < lane.length) & (np.abs(coords[:, 1]) < lane.width / 2 - margin)
            if inside.any():
                closest = float(np.abs(coords[inside, 1]).min())
                found.append({"lane": [str(x) for x in lane.index], "along_m": round(float(coords[inside, 0].min()), 1),
                              "closest_to_centre_m": round(closest, 2), "touches_centred_car": closest < CAR_HALF_WIDTH})
    return found


def roads_with_every_lane_cut(env, lines: list[dict]) -> list[list[str]]:
    """Route roads on which every lane has a line that a centred car touches: a car centred in
    any lane of the road touches a solid line (one off centre might squeeze past)."""
    cut = {tuple(line["lane"]) for line in lines if line["touches_centred_car"]}
    return [[start, end] for start, end, lanes in route_roads(env)
            if all((str(start), str(end), str(lane.index[2])) in cut for lane in lanes)]


def per_episode_success(table: dict | None, runs: Path | None) -> dict[str, np.ndarray]:
    """Each episode's success: of MetaDrive's expert (from the table) and of each seed's run."""
    rows = {}
    if table is not None:
        rows["metadrive-expert"] = np.array(table["baselines"]["metadrive-expert"]["per_episode"]["success_rate"])
    for heldout in sorted(runs.glob("seed_*/heldout.json")) if runs else []:
        rows[heldout.parent.name] = np.array(json.loads(heldout.read_text())["per_episode"]["success_rate"])
    return rows


def compare(rows: dict[str, np.ndarray], flags: list[bool]) -> dict:
    """Mean success of each row on the flagged scenarios and on the others."""
    mask = np.array(flags)
    return {name: {"with": round(float(s[mask].mean()), 3), "without": round(float(s[~mask].mean()), 3)}
            for name, s in rows.items() if len(s) == len(mask)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenarios", type=int, nargs=2, default=[0, 200], metavar=("START", "COUNT"))
    parser.add_argument("--margin", type=float, default=0.3, help="metres inside a lane's edges that count")
    parser.add_argument("--table", help="a drive_recipe.py JSON with per-episode results on the same scenarios")
    parser.add_argument("--runs", type=Path, help="drive_recipe.py's run directory (RUN/seed_N/heldout.json)")
    parser.add_argument("--out")
    args = parser.parse_args()
    started = time.time()
    start, count = args.scenarios
    # MetaDrive's validation scenarios (start seed 0) with no traffic: reset(seed=k) loads scenario k
    gym_env = make_env("MetaDrive-validation-v0", traffic_density=0.0)
    env = gym_env.unwrapped.metadrive
    scenarios = {}
    try:
        for seed in range(start, start + count):
            gym_env.reset(seed=seed)
            lines = lines_in_lanes(env, args.margin)
            scenarios[seed] = {"blocks": "".join(block.ID for block in env.current_map.blocks), "lines": lines,
                               "roads_with_every_lane_cut": roads_with_every_lane_cut(env, lines)}
            print(seed, scenarios[seed]["blocks"], len(lines), scenarios[seed]["roads_with_every_lane_cut"], flush=True)
    finally:
        gym_env.close()
    blocked = [any(line["touches_centred_car"] for line in s["lines"]) for s in scenarios.values()]
    result = {"benchmark": "metadrive-solid-lines", **provenance(started), "scenarios": [start, count],
              "margin_m": args.margin,
              "with_line_touching_a_centred_car": [seed for seed, b in zip(scenarios, blocked) if b],
              "with_every_lane_of_a_road_cut": [seed for seed, s in scenarios.items() if s["roads_with_every_lane_cut"]],
              "per_scenario": scenarios}
    rows = per_episode_success(json.loads(Path(args.table).read_text()) if args.table else None, args.runs)
    if rows:
        every_lane_cut = [bool(s["roads_with_every_lane_cut"]) for s in scenarios.values()]
        result["success"] = {"line_touching_a_centred_car": compare(rows, blocked),
                             "every_lane_of_a_road_cut": compare(rows, every_lane_cut)}
    summary = {k: v for k, v in result.items() if k != "per_scenario"}
    print(json.dumps(summary, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    sys.exit(main())
