#!/usr/bin/env python3
"""What a real UR10's errors are beyond geometry: a study of series A (laser tracker, 3D).

In: ../shared/data/ur10_tracker_series_a/tracker.csv (Landgraf et al., IEEE CASE 2021, MIT).
Out: printed figures for docs/validation.md ("A real UR10: what lies beyond geometry").

Independent of edbbgen's code: the UR10's published DH, a 5-parameter row per joint
(theta, d, a, alpha, and beta on the two parallel axes), the tracker frame and the tracked
point fitted by Gauss-Newton with numerical derivatives, and a weak ridge on the DH deviations
for the parameters the data cannot separate. Scored as tests/ur10_tracker.rs scores
`calibrate`: four contiguous quarters of the series held out in turn; the model fitted to the
rest, registered rigidly to the tracker on the poses it was fitted to, and scored in 3D on the
quarter it never saw.

    python3 -m venv target/study && target/study/bin/pip install numpy
    target/study/bin/python bench/ur10_study.py          # about 5 minutes on 2 cores
"""
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
DATA = os.path.join(HERE, "..", "..", "shared", "data", "ur10_tracker_series_a", "tracker.csv")

table = np.loadtxt(DATA, delimiter=",", skiprows=1)
Q = np.radians(table[:, :6])
X = table[:, 6:9]  # mm, tracker frame
N = len(Q)

# The UR10's published standard DH (mm, rad).
D0 = np.array([127.3, 0, 0, 163.941, 115.7, 92.2])
A0 = np.array([0, -612, -572.3, 0, 0, 0])
AL0 = np.radians([90, 0, 0, 90, -90, 0])
TOOL0 = np.array([0, 0, 93.0])
NG = 6 + 30 + 3  # frame (rotation vector, translation), 6 DH rows of 5, tracked point


def rot(w):
    th = np.linalg.norm(w)
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def dh(th, d, a, al, be):
    n = th.shape[0]
    ct, st, ca, sa = np.cos(th), np.sin(th), np.cos(al), np.sin(al)
    T = np.zeros((n, 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2], T[:, 0, 3] = ct, -st * ca, st * sa, a * ct
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2], T[:, 1, 3] = st, ct * ca, -ct * sa, a * st
    T[:, 2, 1], T[:, 2, 2], T[:, 2, 3], T[:, 3, 3] = sa, ca, d, 1
    if np.any(be != 0):
        cb, sb = np.cos(be), np.sin(be)
        R = np.zeros((n, 4, 4))
        R[:, 0, 0], R[:, 0, 2], R[:, 2, 0], R[:, 2, 2] = cb, sb, -sb, cb
        R[:, 1, 1], R[:, 3, 3] = 1, 1
        T = T @ R
    return T


def forward(p, q, frames=False):
    """Tracked point in the tracker frame (mm) for parameters p at joints q (+ the effects'
    joint errors)."""
    n = q.shape[0]
    g = p[6:36].reshape(6, 5)
    T = np.tile(np.eye(4), (n, 1, 1))
    fs = [T]
    for j in range(6):
        full = lambda v: np.full(n, v)
        T = T @ dh(q[:, j] + g[j, 0], full(D0[j] + g[j, 1]), full(A0[j] + g[j, 2]),
                   full(AL0[j] + g[j, 3]), full(g[j, 4]))
        fs.append(T)
    x = T[:, :3, :3] @ (TOOL0 + p[36:39]) + T[:, :3, 3]
    y = x @ rot(p[:3]).T + p[3:6]
    return (y, fs) if frames else y


def kabsch(a, b):
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.eye(3)
    d[2, 2] = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ d @ u.T
    return r, cb - r @ ca


def log_rot(r):
    th = np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))
    if th < 1e-12:
        return np.zeros(3)
    return th / (2 * np.sin(th)) * np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])


# Start: the nominal robot registered to the tracker.
P0 = np.zeros(NG)
R0, T0 = kabsch(forward(P0, Q), X)
P0[:3], P0[3:6] = log_rot(R0), T0
# Ridge on the DH deviations (1 sigma: 200 deg, 1 m): only for what the data cannot separate.
# beta only on the parallel joints 2 and 3; the others held at 0.
RIDGE = np.tile([np.radians(200), 1000, 1000, np.radians(200), np.radians(200)], 6)
FIXED = np.array([(i % 5 == 4 and i // 5 not in (1, 2)) for i in range(30)])
STEP = np.r_[np.full(3, 1e-6), np.full(3, 1e-3), np.tile([1e-6, 1e-3, 1e-3, 1e-6, 1e-6], 6),
             np.full(3, 1e-3)]


def harmonics(terms):
    """Joint errors dq_j = sum c cos(h q_j) + s sin(h q_j) over terms [(joint, order)]."""
    def dq(c, q):
        out = np.zeros_like(q)
        for k, (j, h) in enumerate(terms):
            out[:, j] += c[2 * k] * np.cos(h * q[:, j]) + c[2 * k + 1] * np.sin(h * q[:, j])
        return out
    return dq, 2 * len(terms)


def fit(rows, effect=None, ne=0):
    p = np.r_[P0, np.zeros(ne)]
    free = np.r_[np.ones(6, bool), ~FIXED, np.ones(3 + ne, bool)]
    h = np.r_[STEP, np.full(ne, 1e-6)][free]
    ridge = np.r_[np.zeros(6), 1 / RIDGE, np.zeros(3), np.full(ne, 1 / 0.01)][free]

    def res(v):
        pp = p.copy()
        pp[free] = v
        q = Q[rows] if effect is None else Q[rows] + effect(pp[NG:], Q[rows])
        return (forward(pp[:NG], q) - X[rows]).ravel()

    v = p[free]
    for _ in range(8):
        r0 = res(v)
        J = np.empty((r0.size, v.size))
        for i in range(v.size):
            w = v.copy()
            w[i] += h[i]
            J[:, i] = (res(w) - r0) / h[i]
        reg = v.copy()
        reg[:6] = 0  # the tracker frame is free
        A = J.T @ J + np.diag(ridge ** 2)
        dv = -np.linalg.solve(A + 1e-9 * np.diag(np.diag(A)), J.T @ r0 + ridge ** 2 * reg)
        v = v + dv
        if np.max(np.abs(dv / h)) < 1e-2:
            break
    p[free] = v
    return p


def held_out(effect=None, ne=0, blocks=4):
    out = []
    for b in range(blocks):
        lo, hi = b * N // blocks, (b + 1) * N // blocks
        test = np.arange(lo, hi)
        train = np.r_[np.arange(lo), np.arange(hi, N)]
        p = fit(train, effect, ne)
        q = Q if effect is None else Q + effect(p[NG:], Q)
        y = forward(p[:NG], q)
        r, t = kabsch(y[train], X[train])
        e = np.linalg.norm(y @ r.T + t - X, axis=1)
        out.append(1e3 * np.sqrt((e[test] ** 2).mean()))
    return np.array(out)


def spectrum(p, top=6, orders=60):
    """Per joint, the single harmonic orders of its own angle that take most of the geometric
    fit's residual (share of the residual's sum of squares, amplitude in arcsec)."""
    y, fs = forward(p, Q, frames=True)
    e = (X - y).ravel()
    tip = fs[6][:, :3, :3] @ (TOOL0 + p[36:39]) + fs[6][:, :3, 3]
    r = rot(p[:3])
    for j in range(6):
        z, o = fs[j][:, :3, 2], fs[j][:, :3, 3]
        col = np.cross(z, tip - o) @ r.T
        scores = []
        for h in range(1, orders + 1):
            a = np.c_[(col * np.cos(h * Q[:, [j]])).ravel(), (col * np.sin(h * Q[:, [j]])).ravel()]
            c = np.linalg.lstsq(a, e, rcond=None)[0]
            scores.append((1 - ((e - a @ c) ** 2).sum() / (e ** 2).sum(), h, np.hypot(*c) * 206265))
        scores.sort(reverse=True)
        print(f"  joint {j + 1}: " + ", ".join(f"order {h} {100 * s:.0f} % ({a:.0f}\")"
                                                for s, h, a in scores[:top]))


def line(name, v, base=None):
    gain = "" if base is None else f"  ({100 * (1 - v.mean() / base.mean()):+.0f} % on geometry)"
    print(f"{name:<44} " + " ".join(f"{x:4.0f}" for x in v) + f"   mean {v.mean():4.0f} um{gain}",
          flush=True)


if __name__ == "__main__":
    whole = fit(np.arange(N))
    y = forward(whole, Q)
    print(f"{N} poses; nominal {1e3 * np.sqrt(((forward(P0, Q) - X) ** 2).sum(1).mean()):.0f} um RMS,"
          f" geometry fitted to all {1e3 * np.sqrt(((y - X) ** 2).sum(1).mean()):.0f} um")
    print("Harmonic orders of each joint's own angle in the geometric residual:")
    spectrum(whole)
    if "--spectrum" in sys.argv:
        sys.exit()
    print("Held out by quarters (um RMS in 3D on the quarter never fitted):")
    geo = held_out()
    line("geometry", geo)
    for name, terms in [
        ("+ order 17 of joints 1-3", [(j, 17) for j in range(3)]),
        ("+ orders 1-3 of joints 1-5", [(j, h) for j in range(5) for h in (1, 2, 3)]),
        ("+ order 17 of joints 1-5", [(j, 17) for j in range(5)]),
        ("+ orders 1-3 and 17 of joints 1-5", [(j, h) for j in range(5) for h in (1, 2, 3, 17)]),
    ]:
        line(name, held_out(*harmonics(terms)), geo)
