"""The best schedule a constraint solver finds for scenario aip-0-7 on the AIP-PRIMECA cell.

A reference for docs/scheduling.md ("How short can aip-0-7 be?"), not part of the bench:
`bench schedule` measures what the holons do; this model asks what any control could do
with the cell's own figures, so that a gap to the lower bound can be split into what the
cell allows and what the control loses. It is an offline model: no holon, no plant.

The cell, as deploy/cells/aip-primeca ships it, read from its files (`read_cell`):
- the stations the cell starts (cell.toml; M7 is away in scenario 0), their services and
  how long each takes (each action the controller's delay_ms in plant.toml: the
  benchmark's table as the emulator has it);
- the steps of the products the scenario releases (b.toml ... p.toml), each loaded at
  M1, inspected at M5 and unloaded at M1;
- the monorail (monorail.toml): a one-way loop of 16,865 mm at 500 mm/s, the stoppers'
  places along it and where each station, the entry, the exit and the buffer dock, 1 s
  to leave a station's spur and 1 s to dock: a move from a to b takes the distance one
  way round at speed plus 2 s, which the runs' traces match within 0.1 s;
- a station's port has one place, held from the start of the move in until the move
  away begins (docs/material-flow.md, "Reservations" and "Departure"); steps on the same
  station follow one another without a move (the part does not leave and come back);
- a part done at a station may wait at its port (holding it) or ride home to the buffer
  (which always has its place) and on from there later. It may wait at its port as long
  as it likes: our control bounds that wait and yields the port to a part that wants it
  (docs/material-flow.md, "Orders arrange their moves"), a rule of the control, not of
  the cell.
Neither the ten shuttles nor the loop's queues are counted (seven parts, ten shuttles).

Three cells are modelled (--cell):
- `as-shipped`: the above;
- `waiting-place`: each station also has one waiting place in front of its port: a part
  may ride there (holding it from the start of that move) and move in within 2 s once
  the port frees (docs/scheduling.md, "The next lever"); the model lets a part ride
  there only from the station before, not from home, so it gives this cell less than
  the design would;
- `free-waiting`: a part may wait anywhere just short of a station without holding
  anything and move in within 1 s (the dock): not a cell anyone can build, a relaxation
  that bounds what waiting places of any number could give.

--travel F multiplies every move's time (1: the cell as shipped); the bench's lower bound
for the same travel is printed beside it (its busiest set, {M2, M3}: the least head,
their 250 s of work shared by two, the least tail; docs/scheduling.md, "The lower bound").
That bound is written out for aip-0-7's busiest set, not derived from the files: a
change to the cell's stations or products needs it written again (or the bench's own).

The solver (CP-SAT, Google OR-Tools) returns the best schedule it found within its time
(--seconds): a makespan no control can beat on the modelled cell only when it reports
OPTIMAL; FEASIBLE is an upper bound of the best, and its own lower bound is weak.

Run it (from the repository's root):
    python3 -m venv target/model-venv && target/model-venv/bin/pip install ortools==9.15.6755
    target/model-venv/bin/python bench/models/aip_0_7_schedule.py --cell as-shipped --seconds 900
"""

import argparse
import math
import pathlib
import tomllib

from ortools.sat.python import cp_model

REPO = pathlib.Path(__file__).resolve().parents[2]
SCENARIO = REPO / "deploy/scenarios/aip-0-7.toml"


def read_toml(path):
    with open(path, "rb") as f:
        return tomllib.load(f)


def read_cell(scenario_path):
    """The cell's figures, from its own files: the loop (stoppers' places, length, speed,
    docking; where the entry, exit and buffer dock), each station the cell starts (its
    stopper, its services and how long each takes on its controller in plant.toml), and
    the steps of each product the scenario releases."""
    scenario = read_toml(scenario_path)
    cell_dir = (scenario_path.parent / scenario["cell"]).resolve()
    plant = read_toml(cell_dir / "plant.toml")
    delay_ms = {c["resource"]: c.get("delay_ms", 0) for c in plant["controller"]}
    if any("action_ms" in c for c in plant["controller"]):
        raise SystemExit("plant.toml times some actions apart (action_ms): not modelled")
    configs = {}
    for process in read_toml(cell_dir / "cell.toml")["process"]:
        args = process.get("args", [])
        if "--config" in args:
            configs[process["name"]] = read_toml(cell_dir / args[args.index("--config") + 1])
    stopper_mm, duration_s, able, docks = {}, {}, {}, {}
    for name, config in configs.items():
        layout = config.get("layout", {})
        if "conveyor" in layout:
            loop = layout["conveyor"]
            stopper_mm = {st["name"]: st["at_mm"] for st in loop["stoppers"]}
            loop_mm, speed, dock_s = loop["length_mm"], loop["speed_mm_s"], loop.get("dock_ms", 0) / 1000
            for location in layout.get("locations", []):
                docks[location["role"]] = location["dock"].split(".")[1]
        elif "services" in config:
            port = next(loc for loc in layout["locations"] if loc["role"] == "port")
            docks[name] = port["dock"].split(".")[1]
            for service, spec in config["services"].items():
                duration_s[service] = len(spec["steps"]) * delay_ms[name] / 1000
                able.setdefault(service, []).append(name)
    products = {}
    for release in scenario["releases"]:
        if release.get("count", 1) != 1 or release.get("at_s", 0) != 0:
            raise SystemExit("the model takes one order of each product, released at 0")
        steps = read_toml(cell_dir / f"{release['product']}.toml")["steps"]
        products[release["product"].upper()] = [step["service_type"] for step in steps]
    return dict(stopper_mm=stopper_mm, loop_mm=loop_mm, speed_mm_s=speed, dock_s=dock_s,
                duration_s=duration_s, able=able, docks=docks, products=products)


CELL = read_cell(SCENARIO)
# The loop: each place's stopper along it (mm; stations by name, the entry, exit and
# buffer by their roles), its length and its pallets' speed.
LOOP_MM = CELL["loop_mm"]
SPEED_MM_S = CELL["speed_mm_s"]
DOCK_S = CELL["dock_s"]
STOPPER_MM = {place: CELL["stopper_mm"][stopper] for place, stopper in CELL["docks"].items()}
STATIONS = sorted(s for s in CELL["docks"] if s not in ("entry", "exit", "buffer"))
# How long each service takes (s), and the stations that offer it.
DURATION_S = CELL["duration_s"]
ABLE = CELL["able"]
# Each product's steps, load to unload.
PRODUCTS = CELL["products"]
TICKS_PER_S = 10
HORIZON = 900 * TICKS_PER_S
# Moving in from a waiting place, and from just short of a station (free-waiting).
WAITING_PLACE_MOVE_IN_S = 2.0
FREE_WAITING_MOVE_IN_S = DOCK_S
# What a port stays held after the move away begins: the plant frees it as the pallet
# leaves it, when the move begins (the next track counts the second back onto the loop),
# and the monorail reports the departure at once (docs/material-flow.md, "Departure").
DEPARTURE_S = 0.0


def move_s(a, b, travel):
    """A move's time from stopper a to stopper b, unobstructed, one way round the loop."""
    if a == b:
        return 0.0
    return (((STOPPER_MM[b] - STOPPER_MM[a]) % LOOP_MM) / SPEED_MM_S + 2 * DOCK_S) * travel


def ticks(seconds):
    """Seconds in ticks, rounded up: no move or step is made shorter than the plant's."""
    return math.ceil(seconds * TICKS_PER_S - 1e-9)


def lower_bound_s(travel):
    """The bench's bound for aip-0-7 (bench/src/schedule/cell/bound.rs): its busiest set
    {M2, M3}, from the least head (entry to M1, load, on to M2; travel without docking) and
    their work shared by two, to the least tail (l_comp on M4, inspection, unload, exit)."""
    run = lambda a, b: ((STOPPER_MM[b] - STOPPER_MM[a]) % LOOP_MM) / SPEED_MM_S * travel
    head = run("entry", "m1") + 10 + run("m1", "m2")
    work = 25 * 20 / 2
    tail = run("m3", "m4") + 20 + run("m4", "m5") + 5 + run("m5", "m1") + 10 + run("m1", "exit")
    return head + work + tail


class Model:
    """The schedule of the seven parts as one CP-SAT model."""

    def __init__(self, cell, travel):
        self.cell = cell
        self.travel = travel
        self.m = cp_model.CpModel()
        # Each station's port (and waiting place): the intervals that hold it.
        self.port = {s: [] for s in STATIONS}
        self.waiting_place = {s: [] for s in STATIONS}
        self.makespan = self.m.NewIntVar(0, HORIZON, "makespan")
        # Each product's operations, their starts and their stations' choice literals.
        self.parts = {}
        for product, steps in PRODUCTS.items():
            self.add_part(product, steps)
        for intervals in list(self.port.values()) + list(self.waiting_place.values()):
            self.m.AddNoOverlap(intervals)
        self.m.Minimize(self.makespan)

    def var(self, name=""):
        return self.m.NewIntVar(0, HORIZON, name)

    def add_part(self, product, ops):
        m, n = self.m, len(ops)
        start = [self.var(f"{product}{i}") for i in range(n)]
        end = [self.var() for _ in range(n)]
        at = []
        for i, op in enumerate(ops):
            m.Add(end[i] == start[i] + ticks(DURATION_S[op]))
            choice = {s: (m.NewBoolVar("") if len(ABLE[op]) > 1 else m.NewConstant(1))
                      for s in ABLE[op]}
            m.AddExactlyOne(choice.values())
            at.append(choice)
        # stays[i]: op i is on the station of op i-1 (no move, no wait between them).
        stays = [None] + [m.NewBoolVar("") for _ in range(1, n)]
        for i in range(1, n):
            both = []
            for s in set(at[i]) & set(at[i - 1]):
                b = m.NewBoolVar("")
                m.AddMultiplicationEquality(b, [at[i - 1][s], at[i][s]])
                both.append(b)
            m.AddMaxEquality(stays[i], both) if both else m.Add(stays[i] == 0)
        # move_in[i]: when the move into op i's port begins; leave[i]: when the part
        # leaves op i's station (its port is held 1 s more).
        move_in, leave = [None] * n, [None] * n
        move_in[0] = self.var()
        m.Add(start[0] >= move_in[0] + ticks(move_s("entry", "m1", self.travel)))
        for i in range(1, n):
            leave[i - 1] = self.leave_and_move(start, end, at, stays, move_in, i)
        leave[n - 1] = self.var()
        m.Add(leave[n - 1] >= end[n - 1])
        m.Add(self.makespan >= leave[n - 1] + ticks(move_s("m1", "exit", self.travel)))
        for i in range(n):
            for s, chosen in at[i].items():
                held_from, held_to = self.var(), self.var()
                if i > 0:
                    m.Add(held_from == start[i]).OnlyEnforceIf([chosen, stays[i]])
                    m.Add(held_from == move_in[i]).OnlyEnforceIf([chosen, stays[i].Not()])
                else:
                    m.Add(held_from == move_in[i]).OnlyEnforceIf(chosen)
                departs = leave[i] + ticks(DEPARTURE_S)
                if i + 1 < n:
                    m.Add(held_to == end[i]).OnlyEnforceIf([chosen, stays[i + 1]])
                    m.Add(held_to == departs).OnlyEnforceIf([chosen, stays[i + 1].Not()])
                else:
                    m.Add(held_to == departs).OnlyEnforceIf(chosen)
                self.port[s].append(
                    m.NewOptionalIntervalVar(held_from, self.var(), held_to, chosen, ""))
        self.parts[product] = (ops, start, at)

    def leave_and_move(self, start, end, at, stays, move_in, i):
        """The way from op i-1's station to op i's: straight there, home first, or (as the
        cell allows) by a waiting place. Returns when the part leaves op i-1's station."""
        m = self.m
        leave, move_in[i] = self.var(), self.var()
        m.Add(leave >= end[i - 1])
        m.Add(start[i] == end[i - 1]).OnlyEnforceIf(stays[i])
        m.Add(move_in[i] == leave).OnlyEnforceIf(stays[i])
        home, waits = m.NewBoolVar(""), m.NewBoolVar("")
        if self.cell == "as-shipped":
            m.Add(waits == 0)
        m.Add(home + waits <= 1)
        m.Add(home == 0).OnlyEnforceIf(stays[i])
        m.Add(waits == 0).OnlyEnforceIf(stays[i])
        straight = [stays[i].Not(), home.Not(), waits.Not()]
        m.Add(move_in[i] == leave).OnlyEnforceIf(straight)
        for a, from_a in at[i - 1].items():
            for b, to_b in at[i].items():
                if a == b:
                    continue
                m.Add(start[i] >= leave + ticks(move_s(a, b, self.travel))).OnlyEnforceIf(
                    [from_a, to_b] + straight)
                m.Add(move_in[i] >= leave + ticks(move_s(a, "buffer", self.travel))).OnlyEnforceIf(
                    [from_a, to_b, home])
                m.Add(start[i] >= move_in[i] + ticks(move_s("buffer", b, self.travel))).OnlyEnforceIf(
                    [from_a, to_b, home])
                if self.cell == "as-shipped":
                    continue
                by_wait = m.NewBoolVar("")
                m.AddMultiplicationEquality(by_wait, [from_a, to_b, waits])
                m.Add(move_in[i] >= leave + ticks(move_s(a, b, self.travel))).OnlyEnforceIf(by_wait)
                last_leg = (WAITING_PLACE_MOVE_IN_S if self.cell == "waiting-place"
                            else FREE_WAITING_MOVE_IN_S)
                m.Add(start[i] >= move_in[i] + ticks(last_leg)).OnlyEnforceIf(by_wait)
                if self.cell == "waiting-place":
                    self.waiting_place[b].append(
                        m.NewOptionalIntervalVar(leave, self.var(), move_in[i], by_wait, ""))
        return leave


def main():
    args = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    args.add_argument("--cell", choices=["as-shipped", "waiting-place", "free-waiting"],
                      default="as-shipped")
    args.add_argument("--travel", type=float, default=1.0,
                      help="every move's time times this (1: the cell as shipped)")
    args.add_argument("--seconds", type=float, default=300, help="the solver's time")
    args.add_argument("--workers", type=int, default=2, help="the solver's threads")
    args.add_argument("--seed", type=int, default=0,
                      help="the solver's random seed (searches differ by it)")
    args = args.parse_args()
    model = Model(args.cell, args.travel)
    solver = cp_model.CpSolver()
    solver.parameters.max_time_in_seconds = args.seconds
    solver.parameters.num_workers = args.workers
    solver.parameters.random_seed = args.seed
    status = solver.Solve(model.m)
    if status not in (cp_model.OPTIMAL, cp_model.FEASIBLE):
        raise SystemExit(f"no schedule found: {solver.StatusName(status)}")
    best = solver.ObjectiveValue() / TICKS_PER_S
    bound = lower_bound_s(args.travel)
    print(f"cell {args.cell}, travel x{args.travel}: {solver.StatusName(status)} "
          f"makespan {best:.1f} s, the bench's bound {bound:.1f} s, gap {100 * (best / bound - 1):+.1f}% "
          f"(the solver's own bound {solver.BestObjectiveBound() / TICKS_PER_S:.1f} s)")
    for product, (ops, start, at) in model.parts.items():
        print(product, " ".join(
            f"{op}@{next(s for s, c in at[i].items() if solver.Value(c))}:{solver.Value(start[i]) / TICKS_PER_S:.1f}"
            for i, op in enumerate(ops)))


if __name__ == "__main__":
    main()
