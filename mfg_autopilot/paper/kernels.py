"""Fused per-row kernels (numba) for the feature maps and the learners' updates.

The numpy formulation (``features.MonomialFeatures`` tables of shape (n, M, 4), then
einsum contractions) makes ~850 small numpy calls per control step for a bank of one
and streams (n, M, 4) temporaries through memory for a bank of 10,000. These kernels
compute, one row (one vehicle's learner) at a time, exactly the quantities the
learners need - the monomials sigma(s), the gradient contracted with the weights,
the velocity-block Hessian trace - without building the tables.

Row independence: every output row is computed by the same compiled per-row
function from that row's inputs only, with every sum taken in a fixed sequential
order (no fast-math, no reassociation), so a row's result does not depend on the
bank size or on whether the bank ran on worker threads (``tests/test_kernels.py``).
A bank of ``PARALLEL_MIN_ROWS`` or more rows (opt-in; default: never) runs the row
loop on numba's worker threads (prange); a vehicle's own controller, a bank of one,
never starts a worker thread.

Symbols as in ``features`` and ``learners``: exponents E (M, 4), scale (4,) with
s_tilde = s / scale, weights w (n, M); states (n, 4) [x_m, y_m, vx_m_s, vy_m_s].
Compiled code is cached on disk (``cache=True``); :func:`warm_up` loads or compiles
every kernel before a control loop starts.

Versus the previous numpy code the results differ at rounding level only (integer
powers by repeated multiplication instead of ``pow``, sequential sums instead of
einsum's/pairwise ones): ``tests/test_kernels.py`` states the tolerances.
"""

from __future__ import annotations

import math
import types

import numpy as np
from numba import njit, prange

__all__ = ["PARALLEL_MIN_ROWS", "feature_tables", "hessian_table", "grad_psi", "hjb_update_rows", "fpk_update_rows",
           "phi_G_plan", "warm_up"]

PARALLEL_MIN_ROWS: int | None = None
"""Banks with at least this many rows run on numba's worker threads (prange); smaller ones - a vehicle's
own controller, a bank of one, in any case - run in the calling thread only. None (the default): never.
Measured on the shared 2-core machine (docs/benchmarks.md, third round): with other jobs running, the
threaded simulator at N = 10,000 was slower than the single-threaded one (OpenMP workers spin-waiting
for a busy core; the workqueue layer too), so threads are opt-in (e.g. 512 on a dedicated machine)."""

_CHUNK_ROWS = 32
"""Rows per scratch allocation (and per unit of work on the worker threads)."""


def _variants(impl):
    """(in the calling thread, on worker threads) compilations of one row loop written with prange.
    The threaded one compiles a copy of the function under another qualified name: numba's on-disk
    cache is keyed by it, and would otherwise hand the single-threaded code to both."""
    par = types.FunctionType(impl.__code__, impl.__globals__, impl.__name__ + "_threads", impl.__defaults__, impl.__closure__)
    par.__qualname__ = impl.__qualname__ + "_threads"
    return njit(cache=True)(impl), njit(cache=True, parallel=True)(par)


# -- one row's monomials --------------------------------------------------------------------------
@njit(cache=True, inline="always")
def _powers(s, scale, D, pw):
    """pw[d, k] = (s_d / scale_d)^k, k = 0..D (repeated multiplication)."""
    for d in range(4):
        st = s[d] / scale[d]
        pw[d, 0] = 1.0
        for k in range(1, D + 1):
            pw[d, k] = pw[d, k - 1] * st


# Per monomial x^a y^b vx^c vy^d the factors are f_d = st_d^e, df_d = e st_d^(e-1), d2f_d = e (e-1) st_d^(e-2),
# multiplied in the order of the former numpy tables; the chain rule's 1 / scale factors are multiplied
# (reciprocals computed once per row) instead of divided. Three specialisations (value; + gradient;
# + velocity Hessian), inlined into the row loops.
@njit(cache=True, inline="always")
def _row_sigma(s, E, scale, D, pw, sig):
    """sig (M,) = sigma(s)."""
    _powers(s, scale, D, pw)
    for m in range(E.shape[0]):
        sig[m] = pw[0, E[m, 0]] * pw[1, E[m, 1]] * pw[2, E[m, 2]] * pw[3, E[m, 3]]


@njit(cache=True, inline="always")
def _row_sigma_grad(s, E, scale, D, pw, sig, J):
    """sig (M,) = sigma(s), J (M, 4) = d sigma / d s."""
    _powers(s, scale, D, pw)
    i0, i1, i2, i3 = 1.0 / scale[0], 1.0 / scale[1], 1.0 / scale[2], 1.0 / scale[3]
    for m in range(E.shape[0]):
        e0, e1, e2, e3 = E[m, 0], E[m, 1], E[m, 2], E[m, 3]
        f0, f1, f2, f3 = pw[0, e0], pw[1, e1], pw[2, e2], pw[3, e3]
        sig[m] = f0 * f1 * f2 * f3
        J[m, 0] = e0 * pw[0, max(e0 - 1, 0)] * f1 * f2 * f3 * i0
        J[m, 1] = e1 * pw[1, max(e1 - 1, 0)] * f0 * f2 * f3 * i1
        J[m, 2] = e2 * pw[2, max(e2 - 1, 0)] * f0 * f1 * f3 * i2
        J[m, 3] = e3 * pw[3, max(e3 - 1, 0)] * f0 * f1 * f2 * i3


@njit(cache=True, inline="always")
def _row_features(s, E, scale, D, pw, sig, J, H22, H33, H23):
    """sig (M,) = sigma(s), J (M, 4) = d sigma / d s, and the velocity block of the Hessian
    d^2 sigma / dv dv: H22 = d2/dvx2, H33 = d2/dvy2, H23 = d2/dvx dvy (M,) each."""
    _powers(s, scale, D, pw)
    i0, i1, i2, i3 = 1.0 / scale[0], 1.0 / scale[1], 1.0 / scale[2], 1.0 / scale[3]
    i22, i33, i23 = 1.0 / (scale[2] * scale[2]), 1.0 / (scale[3] * scale[3]), 1.0 / (scale[2] * scale[3])
    for m in range(E.shape[0]):
        e0, e1, e2, e3 = E[m, 0], E[m, 1], E[m, 2], E[m, 3]
        f0, f1, f2, f3 = pw[0, e0], pw[1, e1], pw[2, e2], pw[3, e3]
        df2 = e2 * pw[2, max(e2 - 1, 0)]
        df3 = e3 * pw[3, max(e3 - 1, 0)]
        sig[m] = f0 * f1 * f2 * f3
        J[m, 0] = e0 * pw[0, max(e0 - 1, 0)] * f1 * f2 * f3 * i0
        J[m, 1] = e1 * pw[1, max(e1 - 1, 0)] * f0 * f2 * f3 * i1
        J[m, 2] = df2 * f0 * f1 * f3 * i2
        J[m, 3] = df3 * f0 * f1 * f2 * i3
        H22[m] = e2 * (e2 - 1) * pw[2, max(e2 - 2, 0)] * f0 * f1 * f3 * i22
        H33[m] = e3 * (e3 - 1) * pw[3, max(e3 - 2, 0)] * f0 * f1 * f2 * i33
        H23[m] = df2 * df3 * f0 * f1 * i23


@njit(cache=True)
def _row_hessian(s, E, scale, D, pw, H):
    """Full Hessian d^2 sigma / ds^2 of one row, H (M, 4, 4) (entries as _row_features' H22, H33, H23)."""
    _powers(s, scale, D, pw)
    f = np.empty(4)
    df = np.empty(4)
    d2f = np.empty(4)
    for m in range(E.shape[0]):
        for d in range(4):
            e = E[m, d]
            f[d] = pw[d, e]
            df[d] = e * pw[d, max(e - 1, 0)]
            d2f[d] = e * (e - 1) * pw[d, max(e - 2, 0)]
        for d in range(4):
            for e in range(d, 4):
                if d == e:
                    h = d2f[d]
                    for k in range(4):
                        if k != d:
                            h = h * f[k]
                else:
                    h = df[d] * df[e]
                    for k in range(4):
                        if k != d and k != e:
                            h = h * f[k]
                h = h * (1.0 / (scale[d] * scale[e]))
                H[m, d, e] = h
                H[m, e, d] = h


@njit(cache=True)
def _dot(a, b):
    """sum_k a_k b_k in a fixed order: four interleaved partial sums, then (s0 + s1) + (s2 + s3)."""
    n = a.shape[0]
    s0 = s1 = s2 = s3 = 0.0
    k = 0
    while k + 4 <= n:
        s0 += a[k] * b[k]
        s1 += a[k + 1] * b[k + 1]
        s2 += a[k + 2] * b[k + 2]
        s3 += a[k + 3] * b[k + 3]
        k += 4
    while k < n:
        s0 += a[k] * b[k]
        k += 1
    return (s0 + s1) + (s2 + s3)


@njit(cache=True)
def _Jt_w(J, w, out):
    """out_d = sum_m J[m, d] w_m, (4,)."""
    g0 = g1 = g2 = g3 = 0.0
    for m in range(J.shape[0]):
        g0 += J[m, 0] * w[m]
        g1 += J[m, 1] * w[m]
        g2 += J[m, 2] * w[m]
        g3 += J[m, 3] * w[m]
    out[0], out[1], out[2], out[3] = g0, g1, g2, g3


# -- tables (the MonomialFeatures API) ----------------------------------------------------------------
def _tables_impl(s, E, scale, D, order, sig, J, Hv):
    n, M = s.shape[0], E.shape[0]
    for c in prange((n + _CHUNK_ROWS - 1) // _CHUNK_ROWS):
        pw = np.empty((4, D + 1))
        H = np.empty((3, M))
        for i in range(c * _CHUNK_ROWS, min(n, (c + 1) * _CHUNK_ROWS)):
            if order == 0:
                _row_sigma(s[i], E, scale, D, pw, sig[i])
            elif order == 1:
                _row_sigma_grad(s[i], E, scale, D, pw, sig[i], J[i])
            else:
                _row_features(s[i], E, scale, D, pw, sig[i], J[i], H[0], H[1], H[2])
                for m in range(M):
                    Hv[i, m, 0, 0] = H[0, m]
                    Hv[i, m, 1, 1] = H[1, m]
                    Hv[i, m, 0, 1] = H[2, m]
                    Hv[i, m, 1, 0] = H[2, m]


_tables_serial, _tables_parallel = _variants(_tables_impl)


def _hessian_impl(s, E, scale, D, H):
    n = s.shape[0]
    for c in prange((n + _CHUNK_ROWS - 1) // _CHUNK_ROWS):
        pw = np.empty((4, D + 1))
        for i in range(c * _CHUNK_ROWS, min(n, (c + 1) * _CHUNK_ROWS)):
            _row_hessian(s[i], E, scale, D, pw, H[i])


_hessian_serial, _hessian_parallel = _variants(_hessian_impl)


def _f64(a) -> np.ndarray:
    # C-contiguous and writeable: one compiled signature per kernel (a read-only view, e.g. from
    # np.broadcast_to, would be another type and load or compile another specialisation)
    return np.require(a, dtype=np.float64, requirements=["C", "W"])


def _i64(a) -> np.ndarray:
    return np.require(a, dtype=np.int64, requirements=["C", "W"])


def _threads(n: int) -> bool:
    return PARALLEL_MIN_ROWS is not None and n >= PARALLEL_MIN_ROWS


def feature_tables(E: np.ndarray, scale: np.ndarray, s: np.ndarray, order: int):
    """sigma (n, M), and for order >= 1 the gradient (n, M, 4), for order >= 2 the velocity block
    of the Hessian (n, M, 2, 2) (None where not asked for)."""
    s, E, scale = _f64(s), _i64(E), _f64(scale)
    n, M = s.shape[0], E.shape[0]
    sig = np.empty((n, M))
    J = np.empty((n, M, 4) if order >= 1 else (0, M, 4))
    Hv = np.empty((n, M, 2, 2) if order >= 2 else (0, M, 2, 2))
    D = int(E.max()) if E.size else 0
    (_tables_parallel if _threads(n) else _tables_serial)(s, E, scale, D, int(order), sig, J, Hv)
    return sig, (J if order >= 1 else None), (Hv if order >= 2 else None)


def hessian_table(E: np.ndarray, scale: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Full Hessian d^2 sigma / ds^2, (n, M, 4, 4)."""
    s, E, scale = _f64(s), _i64(E), _f64(scale)
    H = np.empty((s.shape[0], E.shape[0], 4, 4))
    D = int(E.max()) if E.size else 0
    (_hessian_parallel if _threads(s.shape[0]) else _hessian_serial)(s, E, scale, D, H)
    return H


# -- grad psi = J(s)^T w ------------------------------------------------------------------------------
def _grad_psi_impl(s, w, E, scale, D, out):
    n, M = s.shape[0], E.shape[0]
    for c in prange((n + _CHUNK_ROWS - 1) // _CHUNK_ROWS):
        pw = np.empty((4, D + 1))
        sr = np.empty(M)
        Jr = np.empty((M, 4))
        for i in range(c * _CHUNK_ROWS, min(n, (c + 1) * _CHUNK_ROWS)):
            _row_sigma_grad(s[i], E, scale, D, pw, sr, Jr)
            _Jt_w(Jr, w[i], out[i])


_grad_psi_serial, _grad_psi_parallel = _variants(_grad_psi_impl)


def grad_psi(E: np.ndarray, scale: np.ndarray, s: np.ndarray, w: np.ndarray) -> np.ndarray:
    """nabla psi(s) = sum_k w_k nabla sigma_k(s) per row, (n, 4); s (n, 4), w (n, M)."""
    s, w, E, scale = _f64(s), _f64(w), _i64(E), _f64(scale)
    out = np.empty((s.shape[0], 4))
    D = int(E.max()) if E.size else 0
    (_grad_psi_parallel if _threads(s.shape[0]) else _grad_psi_serial)(s, w, E, scale, D, out)
    return out


# -- Algorithm 3, step 2 (learners.hjb_update), one row at a time ------------------------------------
@njit(cache=True, inline="always")
def _hjb_row(s, w, phi_g, E, scale, D, prm, GGt, w_new, post, pw, sig, J, H, T, gl, gp):
    """One row of learners.hjb_update. prm = [c0, vo_x, vo_y, c1, c2, c3, c4, mu, c_H, acc_max].
    Writes w_new (M,) and post = [H_hat, active, dpsi/dx, dpsi/dy, dpsi/dvx, dpsi/dvy, lap_v psi]
    with the gradient and the velocity Laplacian of psi taken with the NEW weights.
    Scratch: pw (4, D + 1), sig (M,), J (M, 4), H (3, M), T (M,), gl (M,), gp (4,)."""
    c0, vo0, vo1, c1, c2, c3, c4, mu, c_H, acc_max = (prm[0], prm[1], prm[2], prm[3], prm[4], prm[5], prm[6],
                                                       prm[7], prm[8], prm[9])
    M = E.shape[0]
    _row_features(s, E, scale, D, pw, sig, J, H[0], H[1], H[2])
    for m in range(M):                  # tr(G G^T hess sigma_k)
        T[m] = H[0, m] * GGt[0, 0] + H[2, m] * GGt[0, 1] + H[2, m] * GGt[1, 0] + H[1, m] * GGt[1, 1]
    _Jt_w(J, w, gp)                     # grad psi with the old weights
    vx, vy = s[2], s[3]
    f00, f01 = vx, vy                   # A s + B c0 v_o
    f02 = (0.0 - c0 * vx) + c0 * vo0
    f03 = (0.0 - c0 * vy) + c0 * vo1
    p0, p1 = gp[2], gp[3]               # B^T grad psi
    rn = math.sqrt(s[0] * s[0] + s[1] * s[1])
    proj = (vx * s[0] + vy * s[1]) / rn if rn > 0 else 0.0
    phi_L = proj + c1 * (rn * rn) + c2 * (vx * vx + vy * vy)
    H_hat = ((f00 * gp[0] + f01 * gp[1] + f02 * gp[2] + f03 * gp[3]) - (p0 * p0 + p1 * p1) / (4 * c3)
             + 0.5 * _dot(w, T) + phi_L + c4 * phi_g)
    # grad_w of l_H = H_hat^2 / 2, normalised
    inv_2c3 = 1.0 / (2 * c3)
    for m in range(M):
        dH = ((J[m, 0] * f00 + J[m, 1] * f01 + J[m, 2] * f02 + J[m, 3] * f03)
              - (J[m, 2] * p0 + J[m, 3] * p1) * inv_2c3 + 0.5 * T[m])
        gl[m] = H_hat * dH
    nrm = math.sqrt(_dot(gl, gl))
    # regulariser R = max(0, s~^T ds~/dt), nominal drift under the saturated a*
    u0, u1 = -p0 / (2.0 * c3), -p1 / (2.0 * c3)
    un = math.sqrt(u0 * u0 + u1 * u1)
    sat = min(1.0, acc_max / max(un, 1e-300))
    a0, a1 = u0 * sat, u1 * sat
    ds2 = (a0 - c0 * vx) + c0 * vo0
    ds3 = (a1 - c0 * vy) + c0 * vo1
    st0, st1, st2, st3 = s[0] / scale[0], s[1] / scale[1], s[2] / scale[2], s[3] / scale[3]
    R = st0 * (vx / scale[0]) + st1 * (vy / scale[1]) + st2 * (ds2 / scale[2]) + st3 * (ds3 / scale[3])
    active = R > 0
    step = mu / nrm if nrm > 0 else 0.0
    for m in range(M):
        w_new[m] = w[m] - step * gl[m]
    if active:
        # d sat(u) / du: I inside the limit, (limit/|u|)(I - u u^T/|u|^2) outside
        D00, D01, D10, D11 = 1.0, 0.0, 0.0, 1.0
        if un > acc_max:
            h0, h1 = u0 / un, u1 / un
            k = acc_max / un
            D00, D01, D10, D11 = k * (1.0 - h0 * h0), k * (0.0 - h0 * h1), k * (0.0 - h1 * h0), k * (1.0 - h1 * h1)
        cf0, cf1 = st2 / scale[2], st3 / scale[3]          # dR / dv
        for m in range(M):
            du0, du1 = -J[m, 2] * inv_2c3, -J[m, 3] * inv_2c3
            gR = cf0 * (D00 * du0 + D01 * du1) + cf1 * (D10 * du0 + D11 * du1)
            w_new[m] = w_new[m] - c_H * gR
    post[0] = H_hat
    post[1] = 1.0 if active else 0.0
    _Jt_w(J, w_new, gp)
    post[2], post[3], post[4], post[5] = gp[0], gp[1], gp[2], gp[3]
    for m in range(M):
        gl[m] = H[0, m] + H[1, m]
    post[6] = _dot(gl, w_new)


def _hjb_rows_impl(s, w, phi_g, E, scale, D, prm, GGt, w_new, post):
    n, M = s.shape[0], E.shape[0]
    for c in prange((n + _CHUNK_ROWS - 1) // _CHUNK_ROWS):
        pw = np.empty((4, D + 1))
        sig = np.empty(M)
        J = np.empty((M, 4))
        H = np.empty((3, M))
        T = np.empty(M)
        gl = np.empty(M)
        gp = np.empty(4)
        for i in range(c * _CHUNK_ROWS, min(n, (c + 1) * _CHUNK_ROWS)):
            _hjb_row(s[i], w[i], phi_g[i], E, scale, D, prm, GGt, w_new[i], post[i], pw, sig, J, H, T, gl, gp)


_hjb_rows_serial, _hjb_rows_parallel = _variants(_hjb_rows_impl)


def hjb_update_rows(E, scale, s, w, phi_g, c0, v_o, c1, c2, c3, c4, mu, c_H, acc_max, GGt):
    """Algorithm 3 step 2 for every row (see learners.hjb_update). Returns w_new (n, M), H_hat (n,),
    active (n,) bool, grad psi (n, 4) and the velocity Laplacian psi_vxvx + psi_vyvy (n,), both with
    the new weights at the same states."""
    s, w, phi_g, E, scale = _f64(s), _f64(w), _f64(phi_g), _i64(E), _f64(scale)
    n = s.shape[0]
    prm = np.array([c0, v_o[0], v_o[1], c1, c2, c3, c4, mu, c_H, acc_max], dtype=np.float64)
    w_new = np.empty_like(w)
    post = np.empty((n, 7))
    (_hjb_rows_parallel if _threads(n) else _hjb_rows_serial)(s, w, phi_g, E, scale, int(E.max()), prm, _f64(GGt), w_new, post)
    return w_new, post[:, 0].copy(), post[:, 1] > 0, np.ascontiguousarray(post[:, 2:6]), post[:, 6].copy()


# -- Algorithm 4, step 3: the FPK model's update at the own state -------------------------------------
@njit(cache=True, inline="always")
def _fpk_row(q, s, a, rate, lap_v_psi, w, E, scale, D, prm, GGt, w_new, pw, sig, J, H, g):
    """F = J_F(q) (b - rate) + sigma_F(q) div b - 1/2 tr(G G^T hess sigma_F(q)) . w_F, b = A s + B (a + c0 v_o),
    div b = -2 c0 - lap_v_psi / (2 c3); w_new = w - mu grad L_F / |grad L_F|. prm = [c0, vo_x, vo_y, c3, mu].
    Scratch: pw (4, D + 1), sig (M,), J (M, 4), H (3, M), g (M,). Returns F."""
    c0, vo0, vo1, c3, mu = prm[0], prm[1], prm[2], prm[3], prm[4]
    M = E.shape[0]
    _row_features(q, E, scale, D, pw, sig, J, H[0], H[1], H[2])
    bc0 = s[2] - rate[0]
    bc1 = s[3] - rate[1]
    bc2 = ((a[0] - c0 * s[2]) + c0 * vo0) - rate[2]
    bc3 = ((a[1] - c0 * s[3]) + c0 * vo1) - rate[3]
    div_b = -2.0 * c0 - lap_v_psi / (2.0 * c3)
    for m in range(M):
        T = H[0, m] * GGt[0, 0] + H[2, m] * GGt[0, 1] + H[2, m] * GGt[1, 0] + H[1, m] * GGt[1, 1]
        g[m] = (J[m, 0] * bc0 + J[m, 1] * bc1 + J[m, 2] * bc2 + J[m, 3] * bc3) + sig[m] * div_b - 0.5 * T
    F = _dot(w, g)
    for m in range(M):
        g[m] = F * g[m]
    nrm = math.sqrt(_dot(g, g))
    step = mu / nrm if nrm > 0 else 0.0
    for m in range(M):
        w_new[m] = w[m] - step * g[m]
    return F


def _fpk_rows_impl(q, s, a, rate, lap, w, E, scale, D, prm, GGt, w_new, F):
    n, M = q.shape[0], E.shape[0]
    for c in prange((n + _CHUNK_ROWS - 1) // _CHUNK_ROWS):
        pw = np.empty((4, D + 1))
        sig = np.empty(M)
        J = np.empty((M, 4))
        H = np.empty((3, M))
        g = np.empty(M)
        for i in range(c * _CHUNK_ROWS, min(n, (c + 1) * _CHUNK_ROWS)):
            F[i] = _fpk_row(q[i], s[i], a[i], rate[i], lap[i], w[i], E, scale, D, prm, GGt, w_new[i], pw, sig, J, H, g)


_fpk_rows_serial, _fpk_rows_parallel = _variants(_fpk_rows_impl)


def fpk_update_rows(E, scale, q, s, a, rate, lap_v_psi, w_F, c0, v_o, c3, mu, GGt):
    """Algorithm 4 step 3 for every row: q (n, 4) the own state in the FPK model's frame (s - s_bar),
    s (n, 4) the own state for the drift b = A s + B (a + c0 v_o) with a (n, 2), rate (n, 4) d s_bar / dt,
    lap_v_psi (n,) psi_vxvx + psi_vyvy. Returns the new w_F (n, M) and the residual F (n,)."""
    q, s, a, rate, lap, w = _f64(q), _f64(s), _f64(a), _f64(rate), _f64(lap_v_psi), _f64(w_F)
    E, scale = _i64(E), _f64(scale)
    n = q.shape[0]
    prm = np.array([c0, v_o[0], v_o[1], c3, mu], dtype=np.float64)
    w_new = np.empty_like(w)
    F = np.empty(n)
    (_fpk_rows_parallel if _threads(n) else _fpk_rows_serial)(q, s, a, rate, lap, w, E, scale, int(E.max()), prm, _f64(GGt),
                                                              w_new, F)
    return w_new, F


# -- eq. 11 over the plan's particles within a radius, FPK-weighted ----------------------------------
@njit(cache=True)
def _cell_of(v, cell):
    return np.int64(math.floor(v / cell))


@njit(cache=True)
def _first_at_least(a, v):
    """First index k with a[k] >= v in the ascending a (a.size if none)."""
    lo, hi = 0, a.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, inline="always")
def _key_start(skey, start, k):
    """First position in the cell-sorted particles whose cell key is >= k: start[k] from the dense table,
    or a binary search in the sorted keys (skey) when the grid is too sparse for a table (start empty)."""
    if start.shape[0] > 0:
        return start[k]
    return _first_at_least(skey, k)


@njit(cache=True)
def _row_pairs(xi, yi, x, own_j, cell, r2, order, skey, start, cxmin, cxmax, cymin, cymax, ny, out):
    """The particles j != own_j with |r_j - (xi, yi)|^2 <= r2, ascending, into out (empty: count only).
    Candidates from the 3 x 3 cells around (xi, yi) of the grid of side cell >= radius."""
    ci, cj = _cell_of(xi, cell), _cell_of(yi, cell)
    lo_y, hi_y = max(cj - 1, cymin), min(cj + 1, cymax)
    c = 0
    if lo_y > hi_y:
        return 0
    for gx in range(max(ci - 1, cxmin), min(ci + 1, cxmax) + 1):
        a = _key_start(skey, start, (gx - cxmin) * ny + (lo_y - cymin))
        b = _key_start(skey, start, (gx - cxmin) * ny + (hi_y - cymin) + 1)
        for t in range(a, b):
            j = order[t]
            dx, dy = x[j, 0] - xi, x[j, 1] - yi
            if dx * dx + dy * dy <= r2 and j != own_j:
                if out.shape[0] > 0:
                    k = c                   # insertion into the ascending list
                    while k > 0 and out[k - 1] > j:
                        out[k] = out[k - 1]
                        k -= 1
                    out[k] = j
                c += 1
    return c


@njit(cache=True)
def _row_pairs_scan(xi, yi, x, own_j, r2, out):
    """As _row_pairs by a scan over every particle (ascending j by construction)."""
    c = 0
    for j in range(x.shape[0]):
        dx, dy = x[j, 0] - xi, x[j, 1] - yi
        if dx * dx + dy * dy <= r2 and j != own_j:
            if out.shape[0] > 0:
                out[c] = j
            c += 1
    return c


_SCAN_MAX_PAIRS = 1 << 16
"""Up to this many (row, particle) candidates the pairs come from a scan over all particles; beyond,
from a cell grid (the same pairs in the same order either way)."""


def _phi_G_impl(own, own_index, x, centroid, E, scale, D, w_F, radius, eps, beta, learn_fpk, phi, npairs):
    """Pairs (row i, particle j != own_index[i]) with |r_j - r_i|^2 <= radius^2, each row's pairs taken
    in ascending j; omega_ij = max(sigma_F(x_j - centroid) . w_F,i, 0) (1 without the FPK model),
    phi_i = sum_j (omega_ij / sum_j omega_ij) k(s_i, x_j) (1 / count if the sum is 0)."""
    n, N, M = own.shape[0], x.shape[0], E.shape[0]
    cell = radius * 1.000001            # >= radius with margin: a pair within radius is in adjacent cells
    r2 = radius * radius
    scan = n * N <= _SCAN_MAX_PAIRS
    # particles sorted by (cell column, cell row), ascending index within a cell
    cxmin = cymin = cxmax = cymax = ny = np.int64(0)
    order = skey = start = np.empty(0, dtype=np.int64)
    if not scan:
        cx = np.empty(N, dtype=np.int64)
        cy = np.empty(N, dtype=np.int64)
        for j in range(N):
            cx[j] = _cell_of(x[j, 0], cell)
            cy[j] = _cell_of(x[j, 1], cell)
        cxmin, cymin = cx.min(), cy.min()
        cxmax, cymax = cx.max(), cy.max()
        ny = cymax - cymin + 1
        key = (cx - cxmin) * ny + (cy - cymin)
        ncell = (cxmax - cxmin + 1) * ny
        if ncell <= 8 * N + 4096:
            # counting sort into a dense table of cell starts (stable: ascending index within a cell)
            start = np.zeros(ncell + 1, dtype=np.int64)
            for j in range(N):
                start[key[j] + 1] += 1
            for k in range(ncell):
                start[k + 1] += start[k]
            fill = start[:-1].copy()
            order = np.empty(N, dtype=np.int64)
            for j in range(N):
                order[fill[key[j]]] = j
                fill[key[j]] += 1
        else:
            order = np.argsort(key, kind="mergesort")
            skey = key[order]
    nch = (n + _CHUNK_ROWS - 1) // _CHUNK_ROWS
    # pass 1: count the pairs of each row
    cnt = np.zeros(n, dtype=np.int64)
    for c in prange(nch):
        none = np.empty(0, dtype=np.int64)
        for i in range(c * _CHUNK_ROWS, min(n, (c + 1) * _CHUNK_ROWS)):
            if scan:
                cnt[i] = _row_pairs_scan(own[i, 0], own[i, 1], x, own_index[i], r2, none)
            else:
                cnt[i] = _row_pairs(own[i, 0], own[i, 1], x, own_index[i], cell, r2, order, skey, start, cxmin, cxmax, cymin,
                                    cymax, ny, none)
    ptr = np.zeros(n + 1, dtype=np.int64)
    for i in range(n):
        ptr[i + 1] = ptr[i] + cnt[i]
    cols = np.empty(ptr[n], dtype=np.int64)
    # pass 2: each row's particles, ascending
    for c in prange(nch):
        for i in range(c * _CHUNK_ROWS, min(n, (c + 1) * _CHUNK_ROWS)):
            if scan:
                _row_pairs_scan(own[i, 0], own[i, 1], x, own_index[i], r2, cols[ptr[i]:ptr[i + 1]])
            else:
                _row_pairs(own[i, 0], own[i, 1], x, own_index[i], cell, r2, order, skey, start, cxmin, cxmax, cymin, cymax,
                           ny, cols[ptr[i]:ptr[i + 1]])
    # sigma_F at the particles used (each once)
    sigF = np.empty((N, M) if learn_fpk else (0, M))
    if learn_fpk:
        used = np.zeros(N, dtype=np.bool_)
        for t in range(cols.size):
            used[cols[t]] = True
        ulist = np.flatnonzero(used)
        for c in prange((ulist.size + _CHUNK_ROWS - 1) // _CHUNK_ROWS):
            pw = np.empty((4, D + 1))
            q = np.empty(4)
            for u in range(c * _CHUNK_ROWS, min(ulist.size, (c + 1) * _CHUNK_ROWS)):
                j = ulist[u]
                for d in range(4):
                    q[d] = x[j, d] - centroid[d]
                _row_sigma(q, E, scale, D, pw, sigF[j])
    # pass 3: the weighted quadrature per row
    for c in prange(nch):
        om = np.empty(0)
        for i in range(c * _CHUNK_ROWS, min(n, (c + 1) * _CHUNK_ROWS)):
            a, b = ptr[i], ptr[i + 1]
            if b == a:
                phi[i] = 0.0
                continue
            if om.shape[0] < b - a:
                om = np.empty(2 * (b - a))
            tot = 0.0
            for t in range(a, b):
                om[t - a] = max(_dot(sigF[cols[t]], w_F[i]), 0.0) if learn_fpk else 1.0
                tot += om[t - a]
            acc = 0.0
            for t in range(a, b):
                j = cols[t]
                dr0, dr1 = x[j, 0] - own[i, 0], x[j, 1] - own[i, 1]
                dv0, dv1 = x[j, 2] - own[i, 2], x[j, 3] - own[i, 3]
                den = eps + (dr0 * dr0 + dr1 * dr1)
                if beta != 1.0:
                    den = den ** beta
                wt = om[t - a] / tot if tot > 0 else 1.0 / (b - a)
                acc += wt * ((dv0 * dv0 + dv1 * dv1) / den)
            phi[i] = acc
    npairs[0] = ptr[n]


_phi_G_serial, _phi_G_parallel = _variants(_phi_G_impl)


def phi_G_plan(own, own_index, x, centroid, E, scale, w_F, radius_m, eps_m2, beta, learn_fpk=True):
    """phi_G(s_i, m_hat) of eq. 11 by quadrature over the plan particles x (N, 4) within radius_m of
    each row's own position (own (n, 4)), its own particle own_index[i] left out, weighted by the
    FPK model max(w_F,i . sigma_F(x_j - centroid), 0) (uniform without it, or if all weights are 0).
    Returns (phi (n,), number of (row, particle) pairs)."""
    own, x, centroid, w = _f64(own), _f64(x), _f64(centroid), _f64(w_F)
    E, scale = _i64(E), _f64(scale)
    n = own.shape[0]
    phi = np.zeros(n)
    npairs = np.zeros(1, dtype=np.int64)
    if n == 0 or x.shape[0] == 0:
        return phi, 0
    (_phi_G_parallel if _threads(n) else _phi_G_serial)(own, _i64(own_index), x, centroid, E, scale, int(E.max()), w,
                                                        float(radius_m), float(eps_m2), float(beta), bool(learn_fpk), phi, npairs)
    return phi, int(npairs[0])


def warm_up() -> None:
    """Load (or, on a cold cache, compile) every single-threaded kernel of this module, so that the first control
    step does not pay for it. Banks of PARALLEL_MIN_ROWS or more compile their threaded variants
    on first use."""
    E = np.array([[1, 0, 2, 0], [0, 1, 0, 2]], dtype=np.int64)
    sc = np.ones(4)
    s = np.full((1, 4), 0.5)
    w = np.ones((1, 2))
    feature_tables(E, sc, s, 2)
    hessian_table(E, sc, s)
    grad_psi(E, sc, s, w)
    G = np.eye(2)
    hjb_update_rows(E, sc, s, w, np.zeros(1), 0.1, np.zeros(2), 1.0, 1.0, 1.0, 1.0, 0.01, 0.5, 2.0, G)
    fpk_update_rows(E, sc, s, s, np.zeros((1, 2)), np.zeros((1, 4)), np.zeros(1), w, 0.1, np.zeros(2), 1.0, 0.01, G)
    phi_G_plan(s, np.zeros(1, dtype=np.int64), np.vstack([s, s + 0.1]), np.zeros(4), E, sc, w, 1.0, 1e-3, 1.0, True)
