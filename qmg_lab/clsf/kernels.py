"""Compiled (numba) per-sample loops of the CLSF estimator, one pass over a block instead of many numpy calls.

Each kernel computes exactly what the vectorised form named in its docstring computes, operation for operation and
in the same order, so that the estimator's results do not depend on which form runs:

* sums follow numpy's own orders: `np.cumsum` and the elementwise ufuncs are sequential; `np.sum` and `np.mean`
  use numpy's pairwise summation (`pairwise_sum`); `np.add.reduceat` adds the pairwise sum of the rest of a
  segment to its first element (`reduceat_sum`);
* the ramp response's exponential is libm's exp, as numpy's float64 exp is on this hardware;
* the five edges' weighted ramps are summed in the order OpenBLAS's x86-64 matrix-vector kernel gives a row of
  five (signed_ramp_sum), where the estimator used to form them as a matrix and multiply it by the signs: the
  kernel now computes H m_d per sample without the n x 5 matrix or the BLAS call;
* the demodulator filter's sections run scipy.signal.sosfilt's direct form II transposed recursion.

Compiled with cache=True (the first import in a fresh environment compiles them once, about a second; later
imports load them from __pycache__). Only the estimator and the edge tracker import this module.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, cast

import numpy as np
from numba import njit, types
from numba.extending import intrinsic

PAIRWISE_BLOCK = 128  # numpy's PW_BLOCKSIZE: below it, eight interleaved partial sums
PAIRWISE_DEPTH = 64  # rows of pairwise_sum's stack: enough for any array length


@njit(cache=True, inline="always")
def _block_sum(a: np.ndarray, lo: int, n: int) -> float:
    """numpy's pairwise_sum for n <= 128: sequential below 8 terms, else eight interleaved partial sums."""
    v = a[lo : lo + n]  # indexed from 0: no negative-index checks in the loops
    if n < 8:
        res = 0.0
        for i in range(n):
            res += v[i]
        return res
    r0, r1, r2, r3 = v[0], v[1], v[2], v[3]
    r4, r5, r6, r7 = v[4], v[5], v[6], v[7]
    m = n - n % 8
    for i in range(8, m, 8):
        r0 += v[i]
        r1 += v[i + 1]
        r2 += v[i + 2]
        r3 += v[i + 3]
        r4 += v[i + 4]
        r5 += v[i + 5]
        r6 += v[i + 6]
        r7 += v[i + 7]
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    for i in range(m, n):
        res += v[i]
    return res


def pairwise_workspace() -> np.ndarray:
    """Scratch space for pairwise_sum's halving stack (allocated once per kernel call, not per sum)."""
    return np.empty((PAIRWISE_DEPTH, 4))


@njit(cache=True, inline="always")
def pairwise_sum(a: np.ndarray, lo: int, n: int, work: np.ndarray) -> float:
    """sum(a[lo:lo+n]) in numpy's pairwise order (np.sum, np.add.reduce of a contiguous float64 array): blocks
    of at most 128 terms (_block_sum), above that the sum of the two halves, the first a multiple of 8 long.

    Up to one halving (two blocks: a dither period's window at 1800 Sa/s) directly, inlined into the calling
    kernel (a call passing arrays costs about as much as summing a block); deeper, _pairwise_stack."""
    if n <= PAIRWISE_BLOCK:
        return _block_sum(a, lo, n)
    half = n // 2
    half -= half % 8
    if n - half <= PAIRWISE_BLOCK:
        return _block_sum(a, lo, half) + _block_sum(a, lo + half, n - half)
    return _pairwise_stack(a, lo, n, work)


@njit(cache=True)
def _pairwise_stack(a: np.ndarray, lo: int, n: int, work: np.ndarray) -> float:
    """pairwise_sum for n > 128, the halving walked with an explicit stack in `work` (pairwise_workspace(); rows:
    start, length, state, value), as numba's cache cannot reload recursive functions."""
    sp, vp = 1, 0  # stack depth, values waiting
    work[0, 0], work[0, 1], work[0, 2] = lo, n, 0.0  # state 0: split next, 1: left half done, 2: both done
    while sp > 0:
        top = sp - 1
        m = int(work[top, 1])
        if m <= PAIRWISE_BLOCK:
            work[vp, 3] = _block_sum(a, int(work[top, 0]), m)
            vp += 1
            sp -= 1
            continue
        half = m // 2
        half -= half % 8
        if work[top, 2] == 0.0:
            work[top, 2] = 1.0
            work[sp, 0], work[sp, 1], work[sp, 2] = work[top, 0], half, 0.0
            sp += 1
        elif work[top, 2] == 1.0:
            work[top, 2] = 2.0
            work[sp, 0], work[sp, 1], work[sp, 2] = work[top, 0] + half, m - half, 0.0
            sp += 1
        else:
            work[vp - 2, 3] = work[vp - 2, 3] + work[vp - 1, 3]
            vp -= 1
            sp -= 1
    return work[0, 3]


@njit(cache=True, inline="always")
def reduceat_sum(a: np.ndarray, lo: int, n: int, work: np.ndarray) -> float:
    """np.add.reduceat's sum of the segment a[lo:lo+n] (n >= 1): its first element plus the pairwise sum of the
    rest."""
    return a[lo] + pairwise_sum(a, lo + 1, n - 1, work)


@njit(cache=True)
def median_spacing(t: np.ndarray, count: int) -> float:
    """np.median(np.diff(t[:count])) for len(t) >= 2: the middle spacing, or the mean of the two middle ones."""
    m = min(count, t.size) - 1
    d = np.empty(m)
    for i in range(m):
        d[i] = t[i + 1] - t[i]
    d.sort()
    if m % 2 == 1:
        return d[m // 2]
    return (d[m // 2 - 1] + d[m // 2]) / 2.0


@njit(cache=True)
def median_spacing_after(t_before: float, t: np.ndarray, count: int) -> float:
    """median_spacing of the sequence t_before, t[0], t[1], ... (np.median(np.diff(np.concatenate(([t_before],
    t))[:count])), for len(t) >= 1)."""
    m = min(count - 1, t.size)
    d = np.empty(m)
    prev = t_before
    for i in range(m):
        d[i] = t[i] - prev
        prev = t[i]
    d.sort()
    if m % 2 == 1:
        return d[m // 2]
    return (d[m // 2 - 1] + d[m // 2]) / 2.0


@njit(cache=True, inline="always")
def _trapezoid_term(
    h: float, x: float, x_prev: float, aux: float, a_prev: float, window_s: float
) -> tuple[float, float]:
    """integrate_block's increments of int x and m_r over one spacing h: h (x + x_prev) / 2 and
    h ((a + a_prev) / 2 + (a - a_prev) W / (2 h)) (the latter term 0 where h = 0)."""
    shift = 0.5 * window_s / h if h > 0 else 0.0
    return 0.5 * h * (x + x_prev), h * (0.5 * (aux + a_prev) + (aux - a_prev) * shift)


@njit(cache=True)
def integrate_block(
    t: np.ndarray,
    x: np.ndarray,
    aux: np.ndarray,
    before: tuple[float, float, float, float, float],
    window_s: float,
    tau_s: float,
    sos: np.ndarray,
    zi: np.ndarray,
    zi_per_unit: bool,
    buf: np.ndarray,
    offset: int,
) -> float:
    """A block's rows of the estimator's sample buffer, written to buf[:, offset:offset + n]: t, y, H m_r, m_r;
    returns int x at the block's end. before: t, x, aux, int x and m_r at the sample before t[0] (for a first
    block, t[0], x[0], aux[0], 0, 0).

    With h_k = t_k - t_(k-1) (the trapezoid rule; AuxIn values sit at t_k - W/2, so the line through two readings
    is shifted by s_k = W / (2 h_k), 0 where h_k = 0):
        int x_k = ix0 + sum_(i<=k) h_i (x_i + x_(i-1)) / 2
        m_r,k   = mr0 + sum_(i<=k) h_i ((a_i + a_(i-1)) / 2 + (a_i - a_(i-1)) s_i)
        y_k     = x_k + int x_k / tau
    (running sums: np.cumsum's sequential order). H m_r: m_r through the filter's second-order sections sos (no
    rows: no filter, H m_r = m_r) from their states zi, updated in place: scipy.signal.sosfilt(sos, m_r, zi=zi)'s
    direct form II transposed recursion, y = b0 u + z0; z0 = b1 u - a1 y + z1; z1 = b2 u - a2 y. A filter of
    one first-order section (order 1: b2 = a2 = 0, z1 = 0) runs in the integrals' loop as _first_order_section's
    recursion (the filter's dependency chain then overlaps the integrals' work); any other runs after the loop
    over the block (sosfilt_inplace). zi_per_unit: zi holds the states per unit input at rest
    (sos_steady_state) and starts at those times the first m_r."""
    t_prev, x_prev, a_prev, ix0, mr0 = before
    n = x.size
    bt, by, bf, bm = buf[0, offset : offset + n], buf[1, offset : offset + n], buf[2, offset:], buf[3, offset:]
    acc_x = 0.0
    acc_m = 0.0
    ix = ix0
    fused = sos.shape[0] == 1 and sos[0, 2] == 0.0 and sos[0, 5] == 0.0 and zi[0, 1] == 0.0
    b0, b1, a1, z0 = (sos[0, 0], sos[0, 1], sos[0, 4], zi[0, 0]) if fused else (0.0, 0.0, 0.0, 0.0)
    if fused and n and zi_per_unit:  # the state at rest for the first m_r (the loop's first step, done ahead)
        first = 0.0  # 0.0 + the term, as acc_m forms it in the loop (a -0.0 term then sums to +0.0)
        first += _trapezoid_term(t[0] - t_prev, x[0], x_prev, aux[0], a_prev, window_s)[1]
        z0 *= mr0 + first
    for k in range(n):
        h = t[k] - t_prev
        dx, dm = _trapezoid_term(h, x[k], x_prev, aux[k], a_prev, window_s)
        acc_x += dx
        ix = ix0 + acc_x
        acc_m += dm
        u = mr0 + acc_m
        bt[k] = t[k]
        by[k] = x[k] + ix / tau_s
        bm[k] = u
        if fused:  # _first_order_section's recursion, in the integrals' loop: the two chains overlap
            v = b0 * u + z0
            z0 = b1 * u - a1 * v
            u = v
        bf[k] = u
        t_prev, x_prev, a_prev = t[k], x[k], aux[k]
    if fused:
        zi[0, 0], zi[0, 1] = z0, 0.0
    elif sos.shape[0]:
        if n and zi_per_unit:
            zi *= bm[0]
        sosfilt_inplace(sos, bf[:n], zi)
    return ix


@njit(cache=True)
def sosfilt_inplace(sos: np.ndarray, x: np.ndarray, zi: np.ndarray) -> None:
    """scipy.signal.sosfilt(sos, x, zi=zi) in place on x and zi: each section s in turn runs over the whole
    block (the same operations as sample by sample through all sections, its state in registers):
        y = b0 u + z0;  z0 = b1 u - a1 y + z1;  z1 = b2 u - a2 y
    (a first-order section with z1 = 0: _first_order_section)."""
    for s in range(sos.shape[0]):
        b0, b1, b2, a1, a2 = sos[s, 0], sos[s, 1], sos[s, 2], sos[s, 4], sos[s, 5]
        z0, z1 = zi[s, 0], zi[s, 1]
        if b2 == 0.0 and a2 == 0.0 and z1 == 0.0:
            _first_order_section(b0, b1, a1, x, zi[s])
            continue
        for k in range(x.size):
            u = x[k]
            v = b0 * u + z0
            z0 = b1 * u - a1 * v + z1
            z1 = b2 * u - a2 * v
            x[k] = v
        zi[s, 0], zi[s, 1] = z0, z1


@njit(cache=True, inline="always")
def _first_order_section(b0: float, b1: float, a1: float, x: np.ndarray, zi: np.ndarray) -> None:
    """sosfilt_inplace's recursion for a first-order section (b2 = a2 = 0, z1 = 0): y = b0 u + z0;
    z0 = b1 u - a1 y. The full recursion adds z1 = b2 u - a2 y, a signed zero, to z0, which leaves every number
    as it is (w + 0 = w for w != 0; an exact zero may change its sign only, and -0 == 0); leaving that addition
    out of the recursion's dependency chain makes the loop about a third faster."""
    z0 = zi[0]
    for k in range(x.size):
        u = x[k]
        v = b0 * u + z0
        z0 = b1 * u - a1 * v
        x[k] = v
    zi[0], zi[1] = z0, 0.0


def _fma_typing(typingctx: Any, a: Any, b: Any, c: Any) -> tuple[Any, Callable[..., Any]] | None:
    """fused_multiply_add's numba typing and code generation: float64 arguments only, LLVM's llvm.fma."""
    if not all(arg == types.float64 for arg in (a, b, c)):
        return None
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return builder.fma(*args)

    return sig, codegen


# a b + c with one rounding (the FMA instruction, or an exactly rounded software form on a processor without one),
# callable only inside compiled kernels; the cast gives mypy the signature kernels call it with (numba's
# intrinsic object is typed with the typing function's own parameters, the typing context first)
fused_multiply_add = cast("Callable[[float, float, float], float]", intrinsic(_fma_typing))


@njit(cache=True, inline="always")
def ramp_column(tw: np.ndarray, e: float, order: int, tc_s: float, out: np.ndarray) -> None:
    """out[k] = R_n(tw[k] - e) for k < tw.size: the filter's response to a unit ramp starting at the edge e
    (DemodFilter.ramp_response, with its operations: R_n(tau) = tau - n tc + tc e^(-tau/tc) sum_(j<n) (n - j)
    (tau/tc)^j / j! for 0 < tau < 60 tc, tau - n tc beyond, 0 before; tau without a filter, tc = 0).

    tw is sorted, so tau = tw_k - e rises with k: the first sample with tau > 0 (a bisection on that very test)
    and the first with tau >= 60 tc bound the zero, transient and steady ranges; only the transient needs the
    exponential. (The loops index views from 0, which lets the compiler drop negative-index checks.)"""
    n = tw.size
    delay = order * tc_s
    transient_end = 60.0 * tc_s
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) // 2
        if tw[mid] - e > 0.0:
            hi = mid
        else:
            lo = mid + 1
    out[:lo] = 0.0
    i = lo
    if tc_s > 0.0:
        while i < n and tw[i] - e < transient_end:
            x = (tw[i] - e) / tc_s
            acc = 0.0
            term = 1.0
            for j in range(order):
                acc += (order - j) * term
                term = term * x / (j + 1)
            out[i] = tw[i] - e - delay + tc_s * math.exp(-x) * acc
            i += 1
    ts = tw[i:]
    rs = out[i:n]
    for k in range(n - i):
        rs[k] = ts[k] - e - delay


@njit(cache=True, inline="always")
def signed_ramp_sum(r0: float, r1: float, r2: float, r3: float, r4: float, step: float) -> float:
    """sum_j s_j step r_j for the ramp responses r_j at the edges (R_(i-1), F_a, R_i, F_b, R_(i+1)), signs
    s = (+, -, +, -, +): with p_j = r_j (s_j step), (p_0 + p_2) + (p_1 + p_3), then r_4 step added by a fused
    multiply-add (one rounding).

    That order is the one OpenBLAS's double-precision x86-64 matrix-vector kernel (dgemv_t) gives each row of an
    n x 5 product: the earlier estimator formed this sum as such a product, and on those processors the two agree
    bit for bit (tests/unit/test_clsf_kernels.py)."""
    return fused_multiply_add(r4, step, (r0 * step + r2 * step) + (r1 * -step + r3 * -step))


@njit(cache=True)
def period_ratios(
    t: np.ndarray,
    y: np.ndarray,
    mf: np.ndarray,
    edges: np.ndarray,
    k0: np.ndarray,
    k1: np.ndarray,
    lo: float,
    hi: float,
    order: int,
    tc_s: float,
) -> np.ndarray:
    """rho = sum y r / sum (H m) r per period (the estimator's docstring) over its window k0[p] <= k < k1[p] of
    the buffer (t, y, H m_r); edges[p]: the period's (R_(i-1), F_a, R_i, F_b, R_(i+1)); lo, hi: the dither's
    recorded levels; the lock-in's filter 1/(1 + s tc)^order.

    H m_d = lo (t - e_0 - n tc) + signed_ramp_sum of the edges' ramp responses (ramp_at; each edge adds a ramp of
    slope +-(hi - lo)); r = H m_d minus its least-squares line a + b t over the window: with means over it,
    t' = t - mean t, v' = H m_d - mean H m_d, b = sum t' v' / sum t'^2 (0 if sum t'^2 = 0), r = v' - b t'.
    H m = H m_r + H m_d. NaN where sum (H m) r = 0. Sums and means are np.add.reduceat's over each window
    (reduceat_sum).

    Three passes per window: H m_d (stored: two sums read it); the products t'^2 and t' v'; the products
    (H m) r and y r. t' and v' are formed again where they are needed rather than stored (the same subtraction
    of the same operands), so each pass writes at most two arrays."""
    delay_s = order * tc_s
    step = hi - lo
    longest = 0
    for p in range(k0.size):
        longest = max(longest, k1[p] - k0[p])
    work = np.empty((PAIRWISE_DEPTH, 4))
    rho = np.empty(k0.size)
    ramps = np.empty((5, longest))
    md = np.empty(longest)
    p1 = np.empty(longest)
    p2 = np.empty(longest)
    for p in range(k0.size):
        a, b = k0[p], k1[p]
        n = b - a
        tw, yw, mfw = t[a:b], y[a:b], mf[a:b]
        for j in range(5):
            ramp_column(tw, edges[p, j], order, tc_s, ramps[j])
        e0 = edges[p, 0]
        for i in range(n):
            edge_part = signed_ramp_sum(ramps[0, i], ramps[1, i], ramps[2, i], ramps[3, i], ramps[4, i], step)
            md[i] = lo * (tw[i] - e0 - delay_s) + edge_part
        mt = reduceat_sum(tw, 0, n, work) / n
        mv = reduceat_sum(md, 0, n, work) / n
        for i in range(n):
            tcn = tw[i] - mt
            p1[i] = tcn * tcn
            p2[i] = tcn * (md[i] - mv)
        stt = reduceat_sum(p1, 0, n, work)
        stv = reduceat_sum(p2, 0, n, work)
        slope = stv / stt if stt > 0 else 0.0
        for i in range(n):
            r = (md[i] - mv) - (tw[i] - mt) * slope
            p1[i] = (mfw[i] + md[i]) * r
            p2[i] = yw[i] * r
        den = reduceat_sum(p1, 0, n, work)
        num = reduceat_sum(p2, 0, n, work)
        rho[p] = num / den if den != 0.0 else np.nan
    return rho


@njit(cache=True)
def plateau_levels(d: np.ndarray, lo: float, hi: float) -> tuple[float, float]:
    """(lo, hi) updated from a block's plateau readings: the means of the readings above mid + 0.45 span and
    below mid - 0.45 span (mid, span of the current levels); a level with no such reading is kept."""
    mid = 0.5 * (lo + hi)
    span = hi - lo
    above = mid + 0.45 * span
    below = mid - 0.45 * span
    work = np.empty((PAIRWISE_DEPTH, 4))
    high = np.empty(d.size)
    low = np.empty(d.size)
    nh = 0
    nl = 0
    for v in d:
        if v > above:
            high[nh] = v
            nh += 1
        if v < below:
            low[nl] = v
            nl += 1
    new_hi = pairwise_sum(high, 0, nh, work) / nh if nh else hi
    new_lo = pairwise_sum(low, 0, nl, work) / nl if nl else lo
    return new_lo, new_hi


@njit(cache=True)
def level_crossings(
    t: np.ndarray,
    d: np.ndarray,
    lo: float,
    hi: float,
    prev: tuple[float, float, int],
    window_s: float,
    hysteresis: float,
    intermediate: float,
) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """The edges in a block of dither readings d at times t (dither_edges.py): (rising times, falling times, the
    last reading's fraction s, its side). prev = (time, s, side 0/1) of the previous block's last reading, side -1
    when there is none (then its time and s are not used).

    With s_k = (d_k - lo) / (hi - lo): a reading is high above 1 - hysteresis, low below hysteresis, else on the
    side of the last clear one; the first reading's side is the previous block's, or its own (s > 1/2 if unclear).
    At each change of side, k the first reading on the new side: the edge is at the middle of the gap
    t_e = (t_(k-1) + t_k - W) / 2, unless a window holds it: t_e = t_(k-1) - W f_old if window k-1 has a fraction
    f_old > intermediate on the new level, and t_e = t_k - W f_new if window k has intermediate < f_new <
    1 - intermediate (the latter wins)."""
    prev_t, prev_s, prev_side = prev
    span = hi - lo
    rising = np.empty(d.size)
    falling = np.empty(d.size)
    nr = 0
    nf = 0
    # the reading before the loop's first: the previous block's last, or this block's first (its side its own)
    start = 0 if prev_side >= 0 else 1
    tp, sp = (prev_t, prev_s) if prev_side >= 0 else (t[0], (d[0] - lo) / span)
    if prev_side >= 0:
        high = prev_side == 1
    elif sp > 1.0 - hysteresis:
        high = True
    elif sp < hysteresis:
        high = False
    else:
        high = sp > 0.5
    for k in range(start, d.size):
        tk = t[k]
        s = (d[k] - lo) / span
        if s > 1.0 - hysteresis:
            now = True
        elif s < hysteresis:
            now = False
        else:
            now = high
        if now != high:
            frac_new = s if now else 1.0 - s
            frac_old = sp if now else 1.0 - sp
            e = 0.5 * (tp + tk - window_s)
            if window_s > 0.0:
                if frac_old > intermediate:
                    e = tp - window_s * frac_old
                if frac_new > intermediate and frac_new < 1.0 - intermediate:
                    e = tk - window_s * frac_new
            if now:
                rising[nr] = e
                nr += 1
            else:
                falling[nf] = e
                nf += 1
            high = now
        tp, sp = tk, s
    return rising[:nr], falling[:nf], sp, high


@njit(cache=True)
def line_at(hist_t: np.ndarray, hist_j: np.ndarray, j: np.ndarray) -> np.ndarray:
    """The least-squares line t = a + b j through the pairs (hist_j, hist_t), at the indices j (EdgeTracker._line):
    about the last pair (t0, j0), x = j - j0, y = t - t0, slope = sum (x - xm)(y - ym) / sum (x - xm)^2 (0 if the
    latter is 0), t(j) = t0 + ym + slope (j - j0 - xm); the last time when fewer than two pairs."""
    n = hist_t.size
    out = np.empty(j.size)
    if n < 2:
        out[:] = hist_t[n - 1]
        return out
    work = np.empty((PAIRWISE_DEPTH, 4))
    t0 = hist_t[n - 1]
    j0 = hist_j[n - 1]
    x = hist_j - j0
    y = hist_t - t0
    xm = pairwise_sum(x, 0, n, work) / n
    ym = pairwise_sum(y, 0, n, work) / n
    dx = x - xm
    sxx = pairwise_sum(dx * dx, 0, n, work)
    slope = pairwise_sum(dx * (y - ym), 0, n, work) / sxx if sxx > 0 else 0.0
    for i in range(j.size):
        out[i] = t0 + ym + slope * (j[i] - j0 - xm)
    return out


@njit(cache=True)
def rolling_line_fit(all_t: np.ndarray, all_j: np.ndarray, start_new: int, fit_edges: int) -> np.ndarray:
    """For each point from start_new on, the least-squares line through it and the fit_edges - 1 points before
    (fewer at the start), evaluated at its own index; the point itself where fewer than 4 points are fitted.

    About the first point (t0, j0): x = j - j0, y = t - t0; with window sums n, Sx, Sy, Sxx, Sxy (differences of
    running sums), slope = (n Sxy - Sx Sy) / (n Sxx - Sx^2) (0 if that is <= 0), intercept = (Sy - slope Sx) / n,
    t = t0 + intercept + slope x."""
    size = all_t.size
    t0 = all_t[0]
    j0 = all_j[0]
    c = np.zeros((5, size + 1))
    for i in range(size):
        x = all_j[i] - j0
        y = all_t[i] - t0
        c[0, i + 1] = c[0, i] + 1.0
        c[1, i + 1] = c[1, i] + x
        c[2, i + 1] = c[2, i] + y
        c[3, i + 1] = c[3, i] + x * x
        c[4, i + 1] = c[4, i] + x * y
    out = np.empty(size - start_new)
    for i in range(start_new, size):
        end = i + 1
        start = max(0, end - fit_edges)
        n = c[0, end] - c[0, start]
        sx = c[1, end] - c[1, start]
        sy = c[2, end] - c[2, start]
        sxx = c[3, end] - c[3, start]
        sxy = c[4, end] - c[4, start]
        den = n * sxx - sx * sx
        slope = (n * sxy - sx * sy) / den if den > 0 else 0.0
        icpt = (sy - slope * sx) / n
        out[i - start_new] = t0 + icpt + slope * (all_j[i] - j0) if n >= 4 else all_t[i]
    return out


@njit(cache=True)
def continue_fit(
    hist_t: np.ndarray, hist_j: np.ndarray, te: np.ndarray, period: float, fit_edges: int
) -> tuple[bool, np.ndarray, np.ndarray]:
    """New edges of one kind continuing a fit's history (the last fit_edges edges, times hist_t at cycle indices
    hist_j): (they follow the line, their cycle indices, their smoothed times).

    Each new edge's index advances by max(1, rint(gap / period)) cycles from the previous edge; when any lies more
    than a quarter period off the history's line (line_at) they do not follow it (the generator was reprogrammed)
    and nothing else is computed; otherwise each is replaced by rolling_line_fit's value."""
    j = np.empty(te.size, dtype=np.int64)
    last_t = hist_t[hist_t.size - 1]
    last_j = np.int64(hist_j[hist_j.size - 1])
    acc = np.int64(0)
    for i in range(te.size):
        step = max(1.0, np.rint((te[i] - last_t) / period))
        acc += np.int64(step)
        j[i] = last_j + acc
        last_t = te[i]
    jf = j.astype(np.float64)
    pred = line_at(hist_t, hist_j, jf)
    for i in range(te.size):
        if abs(te[i] - pred[i]) > 0.25 * period:
            return False, j, te
    all_t = np.concatenate((hist_t, te))
    all_j = np.concatenate((hist_j, jf))
    return True, j, rolling_line_fit(all_t, all_j, hist_t.size, fit_edges)


@njit(cache=True, inline="always")
def _first_at_or_after(a: np.ndarray, v: float, strictly: bool) -> int:
    """np.searchsorted(a, v, side="right" if strictly else "left") on a sorted array."""
    lo, hi = 0, a.size
    while lo < hi:
        mid = (lo + hi) // 2
        if a[mid] < v or (strictly and a[mid] == v):
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True)
def complete_periods(
    rising: np.ndarray, falling: np.ndarray, t: np.ndarray, delay_s: float, min_samples: int
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """The periods [R_i, R_(i+1)) of the edge lists that can be evaluated on the sample times t: (the last i whose
    window [R_i + D, R_(i+1) + D) ends within t, or -1; for the usable ones, the edges (R_(i-1), F_a, R_i, F_b,
    R_(i+1)) and the window's sample range k0 <= k < k1).

    Usable: exactly two falling edges F_a < R_i < F_b between R_(i-1) and R_(i+1), the window starting within t,
    and at least min_samples samples in it."""
    nr, nf = rising.size, falling.size
    done = -1
    edges = np.empty((max(nr - 2, 0), 5))
    k0 = np.empty(max(nr - 2, 0), dtype=np.int64)
    k1 = np.empty(max(nr - 2, 0), dtype=np.int64)
    m = 0
    for i in range(1, nr - 1):
        r_prev, r0, r1 = rising[i - 1], rising[i], rising[i + 1]
        if not r1 + delay_s <= t[t.size - 1]:
            continue
        done = i
        fa = _first_at_or_after(falling, r_prev, True)
        two = (_first_at_or_after(falling, r1, False) - fa == 2) and (r0 + delay_s >= t[0])
        if nf >= 2:
            fc = min(fa, max(nf - 2, 0))
            two = two and (falling[fc] < r0) and (falling[fc + 1] > r0)
        else:
            two = False
        a = _first_at_or_after(t, r0 + delay_s, False)
        b = _first_at_or_after(t, r1 + delay_s, False)
        if two and b - a >= min_samples:
            edges[m, 0], edges[m, 1], edges[m, 2] = r_prev, falling[fa], r0
            edges[m, 3], edges[m, 4] = falling[fa + 1], r1
            k0[m], k1[m] = a, b
            m += 1
    return done, edges[:m], k0[:m], k1[:m]


@njit(cache=True)
def interp_sorted(x: float, xp: np.ndarray, fp: np.ndarray) -> float:
    """np.interp(x, xp, fp) for strictly increasing xp: fp[0] / fp[-1] outside, fp[j] at a node, else
    slope (x - xp[j]) + fp[j] with slope = (fp[j+1] - fp[j]) / (xp[j+1] - xp[j]) (numpy's own formula)."""
    n = xp.size
    if x > xp[n - 1]:
        return fp[n - 1]
    if x < xp[0]:
        return fp[0]
    j = _first_at_or_after(xp, x, True) - 1  # xp[j] <= x < xp[j+1]
    if j >= n - 1 or xp[j] == x:
        return fp[j]
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    res = slope * (x - xp[j]) + fp[j]
    if np.isnan(res):
        res = slope * (x - xp[j + 1]) + fp[j + 1]
        if np.isnan(res) and fp[j] == fp[j + 1]:
            res = fp[j]
    return res


@njit(cache=True)
def mean_rates(edges: np.ndarray, t: np.ndarray, mr: np.ndarray) -> np.ndarray:
    """The rate output averaged over each period [R_i, R_(i+1)] (columns 2 and 4 of edges): the integral m_r
    interpolated linearly at both ends, (m_r(R_(i+1)) - m_r(R_i)) / (R_(i+1) - R_i)."""
    out = np.empty(edges.shape[0])
    for p in range(edges.shape[0]):
        r0, r1 = edges[p, 2], edges[p, 4]
        out[p] = (interp_sorted(r1, t, mr) - interp_sorted(r0, t, mr)) / (r1 - r0)
    return out


@njit(cache=True)
def evaluate_periods(
    rising: np.ndarray,
    falling: np.ndarray,
    buf: np.ndarray,
    held: tuple[int, int],
    lo: float,
    hi: float,
    order: int,
    tc_s: float,
    min_samples: int,
    holds: np.ndarray,
) -> tuple[int, int, int, int, np.ndarray]:
    """The estimator's periods on its buffer rows (t, y, H m_r, m_r), columns held[0]:held[1] (the samples
    held; sample indices below count from held[0]): complete_periods with the filter's delay D = n tc, then
    period_ratios and mean_rates of the usable ones.

    Returns (done, the number usable, the first sample still needed, the number of falling edges still needed,
    and the periods kept as rows R_i, R_(i+1), rho, mean rate output). Kept: a finite rho and no overlap with any
    hold [h0, h1] (a row of holds: h0 <= R_(i+1) and R_i <= h1). Still needed once periods up to `done` are
    evaluated (done >= 0): the rising edges from index done on (the next period's history edge R_done), the
    falling edges after R_done (moved, in order, to the front of `falling`), and the samples from two before the
    first at or after R_(done+1) + D (R_done without a later rising edge) on. (One array out: numba makes a
    Python object of each array it returns, about a microsecond apiece.)"""
    a, b = held  # rows sliced here stay contiguous in numba's types (a 2-D column slice would not)
    t, y, mf, mr = buf[0, a:b], buf[1, a:b], buf[2, a:b], buf[3, a:b]
    delay_s = order * tc_s
    done, edges, k0, k1 = complete_periods(rising, falling, t, delay_s, min_samples)
    usable = edges.shape[0]
    first_needed = 0
    falling_needed = falling.size
    if done >= 0:
        start = rising[done + 1] + delay_s if rising.size - done > 1 else rising[done]
        first_needed = max(0, _first_at_or_after(t, start, False) - 2)
        falling_needed = 0
        for f in falling:
            if f > rising[done]:
                falling[falling_needed] = f
                falling_needed += 1
    rho = period_ratios(t, y, mf, edges, k0, k1, lo, hi, order, tc_s)
    rate = mean_rates(edges, t, mr)
    kept = np.empty((4, usable))
    m = 0
    for p in range(usable):
        ok = np.isfinite(rho[p])
        for h in range(holds.shape[0]):
            if holds[h, 0] <= edges[p, 4] and edges[p, 2] <= holds[h, 1]:
                ok = False
        if ok:
            kept[0, m], kept[1, m], kept[2, m], kept[3, m] = edges[p, 2], edges[p, 4], rho[p], rate[p]
            m += 1
    return done, usable, first_needed, falling_needed, kept[:, :m]


@njit(cache=True)
def period_estimates(rho: np.ndarray, rho_ref: float, gain_correction: float) -> np.ndarray:
    """The estimator's outputs of periods with ratios rho (rows): eta = rho / rho_0 - 1, the scale-factor change
    1 / (1 + eta) - 1 and the gain correction in force (the numpy expressions' operations, one array out)."""
    out = np.empty((3, rho.size))
    for p in range(rho.size):
        eta = rho[p] / rho_ref - 1.0
        out[0, p] = eta
        out[1, p] = 1.0 / (1.0 + eta) - 1.0
        out[2, p] = gain_correction
    return out
