"""Benchmark of mapkit.trajopt against peers, on identical problems.

    .venv/bin/python benchmarks/bench_trajopt.py            # full table (B=256, M=5)
    .venv/bin/python benchmarks/bench_trajopt.py --quick    # fewer repeats, smaller peer subsets

Measures, per trajectory, forward + backward (gradients to key-points and durations) of
``min_snap`` on CPU for the equality path and the corridor path (0.1 m, 5 samples per segment), the
QP backends available for the corridor path, and time allocation (``gradient`` per problem, ``net``
inference). The peers — qpth (OptNet's batched QP layer, with Q + eps*I) and cvxpylayers — live in
the separate environment ``.venv-peers`` built by ``benchmarks/setup_peers.sh`` (qpth pins numpy<2);
they run in a subprocess of that environment on the same problems, written to a temporary .npz in
the coefficient-space form a QP layer needs (min c^T Q c, A c = b, G c <= h, normalised-time basis).
If the peer environment is missing, the table says so and still prints our figures.

This file is also the peer worker: ``--peer-worker IN.npz OUT.npz`` (run with .venv-peers' python;
imports neither mapkit nor anything outside torch/numpy/qpth/cvxpylayers).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import tempfile
import time
from math import factorial
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PEER_PY = ROOT / ".venv-peers" / "bin" / "python"
QPTH_EPS = 1e-6  # the regularisation qpth needs: Q + eps*I (Q is singular on low-order coefficients)


# =============================================================================== peer worker
def _peer_worker(inp: str, out: str, repeats: int, cvx_count: int, threads: int) -> None:
    import torch

    torch.set_num_threads(threads)
    data = np.load(inp)
    res: dict[str, np.ndarray] = {}
    meta: dict[str, object] = {}
    try:
        from qpth.qp import QPFunction
    except Exception as exc:  # noqa: BLE001 - any failure to import the peer is recorded, not fatal
        meta["qpth_error"] = repr(exc)
        QPFunction = None
    for tag in ("eq", "corr"):
        Q = torch.as_tensor(data[f"{tag}_Q"])
        p = torch.as_tensor(data[f"{tag}_p"])
        A = torch.as_tensor(data[f"{tag}_A"])
        b = torch.as_tensor(data[f"{tag}_b"])
        G = torch.as_tensor(data[f"{tag}_G"])
        h = torch.as_tensor(data[f"{tag}_h"])
        B, n = p.shape
        if QPFunction is not None:
            Qe = Q + QPTH_EPS * torch.eye(n, dtype=Q.dtype)
            times = []
            z = None
            for r in range(repeats + 1):
                args = [x.clone().requires_grad_(True) for x in (Qe, p, G, h, A, b)]
                t0 = time.perf_counter()
                try:
                    z = QPFunction(verbose=-1, maxIter=50)(*args)
                    loss = (z * (args[0] @ z.unsqueeze(-1)).squeeze(-1)).sum()
                    loss.backward()
                except Exception as exc:  # noqa: BLE001 - a peer's failure is recorded in the results
                    meta[f"qpth_{tag}_error"] = repr(exc)
                    break
                if r:
                    times.append(time.perf_counter() - t0)
            if times:
                res[f"qpth_{tag}_z"] = z.detach().numpy()
                meta[f"qpth_{tag}_seconds"] = float(np.median(times))
                meta[f"qpth_{tag}_batch"] = B
        # cvxpylayers on a subset (it is slow); objective as ||L c||^2 with L a Cholesky factor
        try:
            import cvxpy as cp
            from cvxpylayers.torch import CvxpyLayer
        except Exception as exc:  # noqa: BLE001 - any failure to import the peer is recorded, not fatal
            meta["cvx_error"] = repr(exc)
            continue
        k = min(cvx_count, B)
        try:
            c = cp.Variable(n)
            Lp = cp.Parameter((n, n))
            pp = cp.Parameter(n)
            Ap = cp.Parameter(tuple(A.shape[1:]))
            bp = cp.Parameter(A.shape[1])
            Gp = cp.Parameter(tuple(G.shape[1:]))
            hp = cp.Parameter(G.shape[1])
            prob = cp.Problem(cp.Minimize(cp.sum_squares(Lp @ c) + pp @ c), [Ap @ c == bp, Gp @ c <= hp])
            layer = CvxpyLayer(prob, parameters=[Lp, pp, Ap, bp, Gp, hp], variables=[c])
            Qr = Q[:k] + 1e-9 * torch.eye(n, dtype=Q.dtype)
            L = torch.linalg.cholesky(Qr).transpose(1, 2)  # c^T Q c = ||L c||^2
            args = [x.clone().requires_grad_(True) for x in (L, p[:k], A[:k], b[:k], G[:k], h[:k])]
            t0 = time.perf_counter()
            (zc,) = layer(*args)
            zc.sum().backward()
            meta[f"cvx_{tag}_seconds"] = time.perf_counter() - t0
            meta[f"cvx_{tag}_batch"] = k
            res[f"cvx_{tag}_z"] = zc.detach().numpy()
        except Exception as exc:  # noqa: BLE001 - a peer's failure is recorded in the results
            meta[f"cvx_{tag}_error"] = repr(exc)[:300]
    res["meta"] = np.array(json.dumps(meta))
    np.savez(out, **res)


# ======================================================================= coefficient-space QP
def _phi(s: float, q: int) -> np.ndarray:
    return np.array([factorial(k) // factorial(k - q) * s ** (k - q) if k >= q else 0.0 for k in range(8)])


def _qhat() -> np.ndarray:
    Q = np.zeros((8, 8))
    for j in range(4, 8):
        for k in range(4, 8):
            Q[j, k] = (factorial(j) // factorial(j - 4)) * (factorial(k) // factorial(k - 4)) / (j + k - 7)
    return Q


def coefficient_qp(w: np.ndarray, T: np.ndarray, corridor: float | None, samples: int):
    """Dense QP in the coefficients c[(i*3 + a)*8 + k] of every element: min c^T Q c, A c = b,
    G c <= h — the same problem min_snap solves (same corridor samples)."""
    B, M1, _ = w.shape
    M = M1 - 1
    n = M * 24
    Qh = _qhat()

    def col(i: int, a: int) -> slice:
        return slice((i * 3 + a) * 8, (i * 3 + a) * 8 + 8)

    Q = np.zeros((B, n, n))
    for i in range(M):
        for a in range(3):
            Q[:, col(i, a), col(i, a)] = Qh[None] * T[:, i, None, None] ** -7.0
    A_rows, b_rows = [], []

    def eq(i: int, a: int, s: float, q: int, value: np.ndarray, i2: int | None = None, s2: float = 0.0):
        row = np.zeros((B, n))
        row[:, col(i, a)] = _phi(s, q)[None] / T[:, i, None] ** q
        if i2 is not None:
            row[:, col(i2, a)] -= _phi(s2, q)[None] / T[:, i2, None] ** q
        A_rows.append(row)
        b_rows.append(value)

    zero = np.zeros(B)
    for a in range(3):
        for q in range(4):
            eq(0, a, 0.0, q, w[:, 0, a] if q == 0 else zero)
            eq(M - 1, a, 1.0, q, w[:, M, a] if q == 0 else zero)
        for i in range(M - 1):
            for q in range(4):
                eq(i, a, 1.0, q, zero, i2=i + 1, s2=0.0)  # continuity
            if corridor is None:
                eq(i, a, 1.0, 0, w[:, i + 1, a])  # through the key-point
    A = np.stack(A_rows, 1)
    b = np.stack(b_rows, 1)
    G_rows, h_rows = [], []
    if corridor is not None:
        s_all = np.concatenate([[0.0], np.arange(1, samples + 1) / (samples + 1), [1.0]])
        for i in range(M):
            u = w[:, i + 1] - w[:, i]
            u = u / np.linalg.norm(u, axis=-1, keepdims=True)
            Pp = np.eye(3)[None] - u[:, :, None] * u[:, None, :]
            centre = np.einsum("bxy,by->bx", Pp, w[:, i])
            for j, s in enumerate(s_all):
                if (i == 0 and j == 0) or (i == M - 1 and j == len(s_all) - 1):
                    continue
                for a in range(3):
                    row = np.zeros((B, n))
                    for bb in range(3):
                        row[:, col(i, bb)] = Pp[:, a, bb, None] * _phi(s, 0)[None]
                    G_rows += [row, -row]
                    h_rows += [centre[:, a] + corridor, -(centre[:, a] - corridor)]
                row = np.zeros((B, n))  # along the segment, within its ends extended by the corridor
                for bb in range(3):
                    row[:, col(i, bb)] = u[:, bb, None] * _phi(s, 0)[None]
                G_rows += [row, -row]
                h_rows += [(u * w[:, i + 1]).sum(-1) + corridor, -((u * w[:, i]).sum(-1) - corridor)]
    else:
        row = np.zeros((B, n))
        row[:, 0] = 1.0  # qpth needs some inequality: a far-away bound on one coefficient
        G_rows.append(row)
        h_rows.append(np.full(B, 1e4))
    return Q, np.zeros((B, n)), A, b, np.stack(G_rows, 1), np.stack(h_rows, 1)


def _cost(Q: np.ndarray, z: np.ndarray) -> np.ndarray:
    return np.einsum("bi,bij,bj->b", z, Q, z)


def _reference(Q, A, b, G, h) -> np.ndarray:
    """High-accuracy reference solve of the coefficient-space QP (Clarabel at 1e-11, else DAQP)."""
    from qpsolvers import Problem, solve_problem

    out = np.zeros((Q.shape[0], Q.shape[1]))
    import importlib.util
    import warnings

    use = "clarabel" if importlib.util.find_spec("clarabel") else "daqp"
    kw = dict(tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11, max_iter=500) if use == "clarabel" else {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for k in range(Q.shape[0]):
            sol = solve_problem(Problem(2 * Q[k], np.zeros(Q.shape[1]), G[k], h[k], A[k], b[k]), solver=use, **kw)
            out[k] = sol.x
    return out, use


def _mp_reference(w: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Minimum snap cost through the key-points, rest to rest, in 40-digit arithmetic: the knot
    form (free interior velocity/acceleration/jerk) built from exact rational basis matrices."""
    import mpmath as mp

    from mapkit.trajopt._basis import _exact_boundary_inverse, _exact_cost

    mp.mp.dps = 40
    ainv = mp.matrix([[mp.mpf(v.numerator) / v.denominator for v in row] for row in _exact_boundary_inverse(4)])
    qh = mp.matrix([[mp.mpf(v.numerator) / v.denominator for v in row] for row in _exact_cost(4)])
    R = ainv.T * qh * ainv
    out = []
    for k in range(w.shape[0]):
        M = T.shape[1]
        N = 4 * (M + 1)
        H = mp.zeros(N, N)
        for i in range(M):
            Ti = mp.mpf(float(T[k, i]))
            sv = [Ti ** q for q in range(4)] * 2
            for a in range(8):
                for c in range(8):
                    H[4 * i + a, 4 * i + c] += Ti ** -7 * sv[a] * sv[c] * R[a, c]
        free = [4 * j + q for j in range(1, M) for q in (1, 2, 3)]
        fixed = [i for i in range(N) if i not in free]
        J = mp.mpf(0)
        for ax in range(3):
            x = mp.zeros(N, 1)
            for j in range(M + 1):
                x[4 * j] = mp.mpf(float(w[k, j, ax]))
            Hff = mp.matrix([[H[i, j] for j in free] for i in free])
            rhs = mp.matrix([-sum(H[i, j] * x[j] for j in fixed) for i in free])
            xf = mp.lu_solve(Hff, rhs)
            for idx, i in enumerate(free):
                x[i] = xf[idx]
            J += (x.T * H * x)[0]
        out.append(float(J))
    return np.array(out)


# ========================================================================================= ours
def _timeit(fn, repeats: int) -> float:
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--segments", type=int, default=5)
    ap.add_argument("--corridor", type=float, default=0.1)
    ap.add_argument("--samples", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--threads", type=int, default=1, help="torch threads for both sides (default 1)")
    ap.add_argument("--quick", action="store_true", help="fewer repeats and smaller slow-solver subsets")
    ap.add_argument("--peer-worker", nargs=2, metavar=("IN", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--cvx-count", type=int, default=8)
    args = ap.parse_args()
    if args.peer_worker:
        _peer_worker(*args.peer_worker, args.repeats, args.cvx_count, args.threads)
        return

    import torch

    from mapkit.trajopt import SOLVERS, TimeAllocationNet, TimeAllocationNetConfig, _qp, allocate_times, min_snap

    torch.set_num_threads(args.threads)
    reps = 3 if args.quick else args.repeats
    B, M = args.batch, args.segments
    g = torch.Generator().manual_seed(0)
    steps = torch.randn(B, M, 3, generator=g, dtype=torch.float64) * 0.6 + torch.tensor([1.0, 0.2, 0.0], dtype=torch.float64)
    w = torch.cat([torch.zeros(B, 1, 3, dtype=torch.float64), torch.cumsum(steps, 1)], 1)
    T = allocate_times(w, "trapezoid", v_max=2.0, a_max=2.0)

    def fwd_bwd(**kw):
        wv = w.clone().requires_grad_(True)
        Tv = T.clone().requires_grad_(True)
        tr = min_snap(wv, Tv, **kw)
        tr.snap_cost().sum().backward()
        return tr

    t_eq = _timeit(lambda: fwd_bwd(), reps) / B
    t_cor = _timeit(lambda: fwd_bwd(corridor=args.corridor, corridor_samples=args.samples), reps) / B
    tr_eq = min_snap(w, T)
    tr_cor = min_snap(w, T, corridor=args.corridor, corridor_samples=args.samples)
    J_eq = tr_eq.snap_cost().numpy()
    J_cor = tr_cor.snap_cost().numpy()
    tr32 = min_snap(w.float(), T.float())
    knots = torch.cat([torch.zeros(B, 1), torch.cumsum(T.float(), 1)], 1)
    res32 = float((tr32.position(knots) - w.float()).abs().max())

    # identical problems in coefficient form (for the peers and the reference solve)
    wn, Tn = w.numpy(), T.numpy()
    eq_qp = coefficient_qp(wn, Tn, None, args.samples)
    cor_qp = coefficient_qp(wn, Tn, args.corridor, args.samples)
    n_ref = B if not args.quick else min(B, 64)
    z_ref, ref_solver = _reference(*[x[:n_ref] for x in (cor_qp[0], cor_qp[2], cor_qp[3], cor_qp[4], cor_qp[5])])
    J_ref = _cost(cor_qp[0][:n_ref], z_ref)
    err_cor = float(np.max(np.abs(J_cor[:n_ref] - J_ref) / J_ref))
    # the equality path's reference: the same minimisation in 40-digit arithmetic (mpmath)
    nb = min(B, 8 if args.quick else 32)
    J_mp = _mp_reference(wn[:nb], Tn[:nb])
    err_eq = float(np.max(np.abs(J_eq[:nb] - J_mp) / J_mp))

    # ---- QP backends on the corridor problems
    solver_rows = []
    import importlib.util
    import warnings

    mods = {"daqp": "daqp", "proxqp": "proxsuite", "clarabel": "clarabel", "piqp": "piqp"}
    nsub = B if not args.quick else min(B, 64)
    for s in SOLVERS:
        if importlib.util.find_spec(mods[s]) is None:
            solver_rows.append((s, "not installed", "", ""))
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t0 = time.perf_counter()
            tr = min_snap(w[:nsub], T[:nsub], corridor=args.corridor, corridor_samples=args.samples,
                          solver=s, on_infeasible="ignore")
            total = time.perf_counter() - t0
        ok = tr.solved.numpy()
        Js = tr.snap_cost().numpy()
        k = min(nsub, n_ref)
        e = np.abs(Js[:k] - J_ref[:k]) / J_ref[:k]
        e = float(np.max(e[ok[:k]])) if ok[:k].any() else float("nan")
        solver_rows.append((s, f"{tr.info['solver_seconds'] / nsub * 1e6:.0f}",
                            f"{total / nsub * 1e6:.0f}", f"{int((~ok).sum())}/{nsub}", f"{e:.1e}"))

    # ---- time allocation
    n_ga = min(B, 5 if args.quick else 20)  # one problem each: a batch smaller than that has no more
    t0 = time.perf_counter()
    for k in range(n_ga):
        allocate_times(w[k], "gradient")
    t_ga = (time.perf_counter() - t0) / n_ga
    net = TimeAllocationNet(TimeAllocationNetConfig(num_segments=M))
    net.eval()
    wf = w[:1].float()
    with torch.no_grad():
        t_net1 = _timeit(lambda: net(wf), 50)
        t_netB = _timeit(lambda: net(w.float()), 20) / B

    # ---- peers
    peer_meta: dict = {}
    peer_res: dict = {}
    peer_note = ""
    if PEER_PY.exists():
        with tempfile.TemporaryDirectory() as td:
            inp = os.path.join(td, "problems.npz")
            outp = os.path.join(td, "peers.npz")
            np.savez(inp, **{f"eq_{k}": v for k, v in zip("QpAbGh", eq_qp, strict=True)},
                     **{f"corr_{k}": v for k, v in zip("QpAbGh", cor_qp, strict=True)})
            cmd = [str(PEER_PY), __file__, "--peer-worker", inp, outp, "--repeats", str(max(1, reps // 2)),
                   "--cvx-count", str(args.cvx_count), "--threads", str(args.threads)]
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
            if proc.returncode != 0 or not os.path.exists(outp):
                peer_note = f"peer run failed: {proc.stderr.strip().splitlines()[-1:] }"
            else:
                with np.load(outp) as d:
                    peer_meta = json.loads(str(d["meta"]))
                    peer_res = {k: d[k] for k in d.files if k != "meta"}
    else:
        peer_note = "peer environment .venv-peers not found: run `bash benchmarks/setup_peers.sh` for peer figures"

    def peer_acc(tag: str, key: str, Jtrue: np.ndarray, qp) -> str:
        if tag == "eq":
            Jtrue = J_mp
        z = peer_res.get(key)
        if z is None:
            return ""
        k = z.shape[0]
        J = _cost(qp[0][:k], z)
        kk = min(k, Jtrue.shape[0])
        rel = float(np.max(np.abs(J[:kk] - Jtrue[:kk]) / Jtrue[:kk]))
        A, b, G, h = qp[2][:k], qp[3][:k], qp[4][:k], qp[5][:k]
        eqv = float(np.max(np.abs(np.einsum("bij,bj->bi", A, z) - b)))
        inv = float(np.max(np.einsum("bij,bj->bi", G, z) - h))
        return f"J rel err {rel:.1e}; |Ac-b| {eqv:.1e}; max(Gc-h) {max(inv, 0):.1e}"

    def peer_cell(key: str, ours: float) -> tuple[str, str]:
        sec = peer_meta.get(f"{key}_seconds")
        batch = peer_meta.get(f"{key}_batch")
        if sec is None:
            if peer_note:
                return "n/a (see note below)", ""
            err = peer_meta.get(f"{key}_error") or peer_meta.get(f"{key.split('_')[0]}_error") or "no result"
            return f"n/a ({str(err)[:40]})", ""
        per = sec / batch
        return f"{per * 1e6:.1f} µs (B={batch})", f"{per / ours:.1f}×"

    qe, qe_r = peer_cell("qpth_eq", t_eq)
    qc, qc_r = peer_cell("qpth_corr", t_cor)
    ce, ce_r = peer_cell("cvx_eq", t_eq)
    cc, cc_r = peer_cell("cvx_corr", t_cor)

    print(f"\nmapkit.trajopt benchmark — CPU, torch threads={args.threads}, B={B}, M={M} segments, 3 axes, float64,")
    print(f"forward + backward (to key-points and durations) per trajectory; corridor {args.corridor} m, "
          f"{args.samples} samples/segment; default QP backend: {_qp.DEFAULT_SOLVER}\n")
    hdr = f"{'case':<34}{'mapkit':>14}  {'target':>8}  {'peer':<28}{'speed-up':>9}  accuracy"
    print(hdr)
    print("-" * len(hdr))
    print(f"{'equality path (closed form)':<34}{t_eq * 1e6:>11.1f} µs  {'≤ 30 µs':>8}  {'':<28}{'':>9}  "
          f"J rel err vs 40-digit {err_eq:.1e}; float32 waypoint residual {res32 * 1e3:.3f} mm")
    print(f"{'  vs qpth (Q + 1e-6 I)':<34}{'':>14}  {'≥ 50×':>8}  {qe:<28}{qe_r:>9}  {peer_acc('eq', 'qpth_eq_z', J_eq, eq_qp)}")
    print(f"{'  vs cvxpylayers':<34}{'':>14}  {'':>8}  {ce:<28}{ce_r:>9}  {peer_acc('eq', 'cvx_eq_z', J_eq, eq_qp)}")
    print(f"{'corridor path (QP + KKT grad)':<34}{t_cor * 1e6:>11.1f} µs  {'≤ 500 µs':>8}  {'':<28}{'':>9}  "
          f"J rel err vs {ref_solver} 1e-11 reference {err_cor:.1e} (n={n_ref})")
    print(f"{'  vs qpth (Q + 1e-6 I)':<34}{'':>14}  {'≥ 4×':>8}  {qc:<28}{qc_r:>9}  {peer_acc('corr', 'qpth_corr_z', J_ref, cor_qp)}")
    print(f"{'  vs cvxpylayers':<34}{'':>14}  {'':>8}  {cc:<28}{cc_r:>9}  {peer_acc('corr', 'cvx_corr_z', J_ref, cor_qp)}")
    print(f"{'time allocation: gradient':<34}{t_ga * 1e3:>11.2f} ms  {'≤ 30 ms':>8}  per 5-segment problem (Mellinger & Kumar, fixed total)")
    print(f"{'time allocation: net inference':<34}{t_net1 * 1e3:>11.3f} ms  {'≤ 0.5 ms':>8}  one problem; "
          f"{t_netB * 1e6:.2f} µs/problem at B={B}")
    if peer_note:
        print(f"\nnote: {peer_note}")
    print(f"\nQP backends on the corridor problems (n={nsub}; µs per problem; J error vs the reference after "
          "the active-set KKT polish):")
    print(f"  {'solver':<10}{'solve':>10}{'end-to-end':>12}{'failed':>10}{'J rel err':>12}")
    for r in solver_rows:
        if len(r) == 4:
            print(f"  {r[0]:<10}{r[1]:>10}")
        else:
            print(f"  {r[0]:<10}{r[1]:>10}{r[2]:>12}{r[3]:>10}{r[4]:>12}")


if __name__ == "__main__":
    main()
