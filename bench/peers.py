"""`make bench-peers`: edbbgen against peer tools on the same instances, from one run.

Reads what `bench --peers DIR` wrote (DIR/tsp_N.txt, DIR/nj130.json) and edbbgen's own figures
(target/bench.json), then
  * solves every TSP instance with LKH-3 (elkai) and OR-tools routing (guided local search);
  * measures Pinocchio forward kinematics and Jacobian throughput on a model built from the same
    NJ-130 DH table (checked against edbbgen's MAP positions first);
and prints edbbgen/peer ratios in one table. A peer that is missing or fails is reported and
skipped; the others still run.

The TSP instances are open paths from a fixed start (pose 0) with a free end, as edbbgen solves
them. They become closed tours the usual way: a dummy node at cost 0 to the start and a large
constant M to every other pose, so every optimal tour enters the start from the dummy and pays M
exactly once at the free end. Costs go to the solvers as integer microseconds; every tour is
re-costed here from the float matrix.
"""

import json
import math
import os
import sys
import time

DIR = sys.argv[1] if len(sys.argv) > 1 else "target/peers"
BENCH = sys.argv[2] if len(sys.argv) > 2 else "target/bench.json"
ORTOOLS_SECONDS_PER_100 = float(os.environ.get("ORTOOLS_SECONDS_PER_100", "1.0"))
LKH_RUNS = int(os.environ.get("LKH_RUNS", "1"))


def read_matrix(path):
    with open(path) as f:
        n = int(f.readline())
        return [[float(x) for x in f.readline().split()] for _ in range(n)]


def path_cost(c, order):
    return sum(c[a][b] for a, b in zip(order, order[1:]))


def closed_instance(c):
    """Integer µs matrix with the dummy node appended as the last index."""
    n = len(c)
    big = int(max(max(r) for r in c) * 1e6) * 10 + 1
    m = [[int(round(v * 1e6)) for v in r] + [big] for r in c]
    m[0][n] = 0
    m.append([0] + [big] * (n - 1) + [0])
    return m


def open_path(tour, n):
    """Closed tour over n+1 nodes (dummy = n) -> open path from 0, or None."""
    if tour and tour[0] == tour[-1]:
        tour = tour[:-1]
    k = tour.index(n)
    t = tour[k + 1:] + tour[:k]
    if t and t[0] == 0:
        return t
    if t and t[-1] == 0:
        return t[::-1]
    return None


def lkh(c):
    import elkai

    n = len(c)
    m = closed_instance(c)
    t0 = time.perf_counter()
    tour = elkai.DistanceMatrix(m).solve_tsp(runs=LKH_RUNS)
    dt = time.perf_counter() - t0
    return open_path(tour, n), dt


def ortools(c):
    from ortools.constraint_solver import pywrapcp, routing_enums_pb2

    n = len(c)
    m = closed_instance(c)
    # Start 0, end at the dummy n: an open path from 0 with a free end.
    manager = pywrapcp.RoutingIndexManager(n + 1, 1, [0], [n])
    routing = pywrapcp.RoutingModel(manager)

    def cost(i, j):
        a, b = manager.IndexToNode(i), manager.IndexToNode(j)
        return 0 if b == n else m[a][b]

    cb = routing.RegisterTransitCallback(cost)
    routing.SetArcCostEvaluatorOfAllVehicles(cb)
    p = pywrapcp.DefaultRoutingSearchParameters()
    p.first_solution_strategy = routing_enums_pb2.FirstSolutionStrategy.PATH_CHEAPEST_ARC
    p.local_search_metaheuristic = routing_enums_pb2.LocalSearchMetaheuristic.GUIDED_LOCAL_SEARCH
    limit = max(2.0, ORTOOLS_SECONDS_PER_100 * n / 100.0)
    p.time_limit.FromMilliseconds(int(limit * 1000))
    t0 = time.perf_counter()
    sol = routing.SolveWithParameters(p)
    dt = time.perf_counter() - t0
    if sol is None:
        return None, dt
    order, i = [], routing.Start(0)
    while not routing.IsEnd(i):
        order.append(manager.IndexToNode(i))
        i = sol.Value(routing.NextVar(i))
    return order, dt


def pinocchio_model(spec):
    import numpy as np
    import pinocchio as pin

    def rot(axis, a):
        ca, sa = math.cos(a), math.sin(a)
        if axis == "z":
            return np.array([[ca, -sa, 0], [sa, ca, 0], [0, 0, 1.0]])
        return np.array([[1.0, 0, 0], [0, ca, -sa], [0, sa, ca]])

    def dh_const(row):
        # RotZ(theta) TransZ(d) TransX(a) RotX(alpha): the constant part of T_i after joint i.
        r = rot("z", row["theta"])
        t = r @ np.array([row["a"], 0.0, row["d"]])
        return pin.SE3(r @ rot("x", row["alpha"]), t)

    model = pin.Model()
    parent, placement = 0, pin.SE3.Identity()
    for i, row in enumerate(spec["dh"]):
        parent = model.addJoint(parent, pin.JointModelRZ(), placement, f"joint{i + 1}")
        placement = dh_const(row)
    tool = placement * pin.SE3(np.eye(3), np.array(spec["map"]))
    try:
        frame = pin.Frame("map", parent, tool, pin.FrameType.OP_FRAME)
    except TypeError:
        frame = pin.Frame("map", parent, 0, tool, pin.FrameType.OP_FRAME)
    fid = model.addFrame(frame)
    return model, fid


def pinocchio_throughput(spec, n_fk=200_000, n_jac=100_000):
    import numpy as np
    import pinocchio as pin

    if not (spec["base_is_identity"] and spec["flange_is_identity"]):
        raise RuntimeError("base/flange transforms are not identity; the DH-only model would differ")
    model, fid = pinocchio_model(spec)
    data = model.createData()
    worst = 0.0
    for c in spec["check"]:
        q = np.array(c["q"])
        pin.forwardKinematics(model, data, q)
        pin.updateFramePlacement(model, data, fid)
        worst = max(worst, float(np.abs(data.oMf[fid].translation - np.array(c["map"])).max()))
    if worst > 1e-9:
        raise RuntimeError(f"Pinocchio MAP differs from edbbgen's by {worst:.3e} m")
    qs = [np.array([x, -x, 0.5 * x, x, -0.3 * x, 2.0 * x]) for x in (k * 1e-6 for k in range(n_fk))]
    best_fk = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        for q in qs:
            pin.forwardKinematics(model, data, q)
            pin.updateFramePlacement(model, data, fid)
        best_fk = min(best_fk, time.perf_counter() - t0)
    best_jac = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        for q in qs[:n_jac]:
            pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL_WORLD_ALIGNED)
        best_jac = min(best_jac, time.perf_counter() - t0)
    # Python loop + call overhead, included in the figures above: a trivial builtin call per pose.
    overhead = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        for q in qs:
            id(q)
        overhead = min(overhead, (time.perf_counter() - t0) / n_fk)
    return n_fk / best_fk, n_jac / best_jac, worst, overhead


def main():
    with open(BENCH) as f:
        ours = json.load(f)
    out = []  # (what, edbbgen, peer, ratio, note)
    tsp = {t["n"]: t for t in ours["tsp"]}
    sizes = sorted(int(f[4:-4]) for f in os.listdir(DIR) if f.startswith("tsp_") and f.endswith(".txt"))
    for k in sizes:
        c = read_matrix(os.path.join(DIR, f"tsp_{k}.txt"))
        n = len(c)
        e = tsp.get(n)
        if e is None:
            print(f"no edbbgen figure for n={n} in {BENCH}", file=sys.stderr)
            continue
        for name, solve in (("LKH-3 (elkai)", lkh), ("OR-tools GLS", ortools)):
            try:
                order, dt = solve(c)
            except ImportError as err:
                print(f"{name}: not installed ({err}); skipped", file=sys.stderr)
                continue
            except Exception as err:  # a peer failing must not stop the others
                print(f"{name} on n={n}: failed ({err}); skipped", file=sys.stderr)
                continue
            if order is None or sorted(order) != list(range(n)):
                print(f"{name} on n={n}: no valid open path; skipped", file=sys.stderr)
                continue
            cost = path_cost(c, order)
            out.append((f"TSP n={n} cost vs {name}", e["cost_s"], cost, e["cost_s"] / cost, "s; <1 = edbbgen shorter"))
            out.append((f"TSP n={n} time vs {name}", e["time_s"], dt, e["time_s"] / dt, "s; <1 = edbbgen faster"))
            print(f"  {name} n={n}: cost {cost:.4f} s in {dt:.2f} s (edbbgen {e['cost_s']:.4f} s in {e['time_s']:.3f} s)", file=sys.stderr)
    try:
        with open(os.path.join(DIR, "nj130.json")) as f:
            spec = json.load(f)
        fk, jac, worst, overhead = pinocchio_throughput(spec)
        ofk, ojac = ours["fk_poses_per_s"]["1"], ours["jacobian_rows_per_s"]["1"]
        out.append(("FK poses/s, 1 thread, vs Pinocchio", ofk, fk, ofk / fk, f">1 = edbbgen faster; peer timed from Python (loop ~{overhead * 1e9:.0f} ns/call included)"))
        out.append(("Jacobian rows/s, 1 thread, vs Pinocchio", ojac, jac, ojac / jac, ">1 = edbbgen faster; 30-param row vs 6x6 frame Jacobian"))
        print(f"  Pinocchio model matches edbbgen's MAP to {worst:.1e} m", file=sys.stderr)
    except ImportError as err:
        print(f"Pinocchio: not installed ({err}); skipped", file=sys.stderr)
    except Exception as err:
        print(f"Pinocchio: failed ({err}); skipped", file=sys.stderr)

    print(f"{'edbbgen vs peer':<44} {'edbbgen':>14} {'peer':>14} {'ratio':>8}  note")
    for what, a, b, r, note in out:
        print(f"{what:<44} {a:>14.6g} {b:>14.6g} {r:>8.4f}  {note}")
    with open(os.path.join(DIR, "peers.json"), "w") as f:
        json.dump([dict(zip(("what", "edbbgen", "peer", "ratio", "note"), o)) for o in out], f, indent=1)


if __name__ == "__main__":
    main()
