"""N4SID subspace identification of discrete-time state-space models from input-output data.

The identified model is the innovation form

    x(k+1) = A x(k) + B u(k) + K e(k)
    y(k)   = C x(k) + D u(k) + e(k)

(with ``u`` and ``y`` taken relative to ``u_offset`` / ``y_offset`` when the data were
detrended). The algorithm (Van Overschee & De Moor, "Subspace identification for linear
systems", 1996):

1. Block Hankel matrices of past and future inputs and outputs (``block_rows`` = i each),
   compressed by an LQ factorisation (computed chunk by chunk, so memory does not grow with
   the record length).
2. Oblique projection O_i of the future outputs along the future inputs onto the past data.
3. SVD of the weighted projection (``weighting``: ``n4sid`` W1 = W2 = I, ``moesp``
   W2 = projection onto the complement of the future inputs, ``cva`` canonical weights);
   the first n left singular vectors give the extended observability matrix Gamma_n.
4. C = first block row of Gamma_n, A from its shift invariance (unstable poles, which only an
   over-fitted or badly excited model has, are reflected into the unit circle: the model is
   meant for simulation and control).
5. B, D and the initial state by linear least squares on the *simulated* output error: the
   simulated output is linear in (x0, B, D) once A and C are known.
6. Noise covariances Q, S, R from the residuals of the Kalman state sequences X_i, X_{i+1}
   estimated from O_i and O_{i-1}; K from the Riccati equation of the steady-state filter.

Order selection (``order=None``): every order k up to ``max_order`` whose singular value is
numerically non-zero is a candidate (its model uses the first k singular directions); the
order minimising BIC = N log(V_k) + p_k log(N) is chosen, with V_k the mean squared simulation
error on the training data and p_k = k (l + m) + l m + k free parameters. The singular values
and the BIC of every candidate are returned so the choice can be inspected.

Block rows (``block_rows=None`` in :func:`identify`): the past and future windows of i samples
must span the slowest transient, yet more rows cost time and variance. Each of
``BLOCK_ROW_CANDIDATES`` the training part is long enough for is tried, and the model with the
lowest training BIC is kept (same criterion, so the order and i are chosen together).

Fit (the paper's figure): ``100 (1 - ||y - yhat|| / ||y - mean(y)||)`` per output, with yhat the
simulated output (not the one-step-ahead prediction). :func:`identify` estimates the model on the
first ``train_fraction`` of the record and reports the fit on the rest (held-out data), the
simulation running through the training part from the estimated initial state, so nothing is
fitted to the held-out samples.

Pure numpy/scipy; no file or clock access (:mod:`hil.controllers.ident.model_file` writes and
reads the model files).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hil.controllers.ident.defaults import BLOCK_ROW_CANDIDATES, DEFAULT_MAX_ORDER

WEIGHTINGS = ("n4sid", "moesp", "cva")
DEFAULT_BLOCK_ROWS = 15

_RANK_RTOL = 1e-10  # singular values below this (relative) count as zero
_ERROR_FLOOR = 1e-20  # relative mean squared error treated as exact (round-off level)
_QR_CHUNK = 8192  # Hankel columns per LQ update


class IdentificationError(ValueError):
    """The data cannot give a model; the message names the signal and the problem."""


@dataclass(frozen=True)
class N4sidResult:
    """Matrices of one N4SID run on (possibly scaled) data, before offsets and names."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    K: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    S: np.ndarray
    x0: np.ndarray
    singular_values: np.ndarray
    block_rows: int
    train_bic: float  # BIC of this model's simulation error on the data it was identified from
    bic: dict[int, float] = field(default_factory=dict)

    @property
    def order(self) -> int:
        return self.A.shape[0]


@dataclass(frozen=True)
class IdentifiedModel:
    """A discrete-time model identified from data, with what is needed to reuse and audit it."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    K: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    S: np.ndarray
    dt: float
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    u_offset: np.ndarray
    y_offset: np.ndarray
    fit_pct_per_output: np.ndarray
    singular_values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    block_rows: int = 0
    samples: dict[str, int] = field(default_factory=dict)
    order_selection: dict[str, Any] = field(default_factory=dict)
    block_rows_selection: dict[str, Any] = field(default_factory=dict)
    command: str = ""
    experiment: str = ""  # the command line that recorded the data, when the session says

    @property
    def order(self) -> int:
        return self.A.shape[0]

    @property
    def fit_pct(self) -> float:
        """Mean held-out fit over the outputs (the fit itself for a single output)."""
        return float(np.mean(self.fit_pct_per_output))

    def simulate(self, u: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
        """Simulated output for inputs ``u`` (samples x inputs, absolute units).

        ``x0`` defaults to zero: at rest when not detrended, at the offsets' operating point when
        detrended.
        """
        u2 = _as_2d(u, "u")
        y = simulate(self.A, self.B, self.C, self.D, u2 - self.u_offset, x0)
        return y + self.y_offset


# -- public algorithm ---------------------------------------------------------------------


def identify(
    u: np.ndarray,
    y: np.ndarray,
    dt: float,
    *,
    inputs: tuple[str, ...] | list[str] | None = None,
    outputs: tuple[str, ...] | list[str] | None = None,
    order: int | None = None,
    max_order: int = DEFAULT_MAX_ORDER,
    block_rows: int | None = None,
    train_fraction: float = 0.7,
    detrend: bool = False,
    feedthrough: bool = True,
    weighting: str = "n4sid",
    command: str = "",
) -> IdentifiedModel:
    """Identify on the first ``train_fraction`` of the record, report the held-out fit.

    ``u``: samples x inputs, ``y``: samples x outputs (1-D arrays mean one signal), sampled
    every ``dt`` seconds. ``detrend`` removes the training means (kept as offsets in the model);
    without it the model maps absolute inputs to absolute outputs (y = 0 at rest for u = 0).
    ``block_rows=None`` tries ``BLOCK_ROW_CANDIDATES`` (those the training part is long enough
    for) and keeps the model with the lowest training BIC; the held-out part decides nothing.
    """
    u2, y2 = _as_2d(u, "u"), _as_2d(y, "y")
    inputs = tuple(inputs) if inputs is not None else tuple(f"u{q}" for q in range(u2.shape[1]))
    outputs = tuple(outputs) if outputs is not None else tuple(f"y{r}" for r in range(y2.shape[1]))
    if len(inputs) != u2.shape[1] or len(outputs) != y2.shape[1]:
        raise IdentificationError("one name per input column and per output column is required")
    if not (dt > 0 and math.isfinite(dt)):
        raise IdentificationError(f"sample period must be a positive number of seconds, got {dt}")
    if not 0 < train_fraction < 1:
        raise IdentificationError(f"train fraction must be between 0 and 1, got {train_fraction}")
    _check_data(u2, y2, inputs, outputs)
    n_total = u2.shape[0]
    n_train = round(n_total * train_fraction)
    n_test = n_total - n_train
    if n_test < 2:
        raise IdentificationError(
            f"train fraction {train_fraction} leaves {n_test} of {n_total} samples for validation"
        )
    u_train, y_train = u2[:n_train], y2[:n_train]
    m, ny = u2.shape[1], y2.shape[1]
    wanted = (block_rows,) if block_rows is not None else _block_row_candidates(order, ny)
    candidates = tuple(i for i in wanted if min_samples(i, m, ny) <= n_train)
    if not candidates:
        raise IdentificationError(
            f"too few samples: the training part ({train_fraction:g} of {n_total}) has "
            f"{n_train} samples, {wanted[0]} block rows with {m} input(s) and {ny} "
            f"output(s) need at least {min_samples(wanted[0], m, ny)}. Record longer or lower "
            "the block rows"
        )
    _check_data(u_train, y_train, inputs, outputs, " in the training part")
    u_off = u_train.mean(axis=0) if detrend else np.zeros(m)
    y_off = y_train.mean(axis=0) if detrend else np.zeros(ny)
    results = {
        i: n4sid(u_train - u_off, y_train - y_off, order, max_order=max_order, block_rows=i,
                 feedthrough=feedthrough, weighting=weighting, inputs=inputs, outputs=outputs)
        for i in candidates
    }
    result = min(results.values(), key=lambda r: r.train_bic)
    y_sim = simulate(result.A, result.B, result.C, result.D, u2 - u_off, result.x0) + y_off
    y_test = y2[n_train:]
    for r, name in enumerate(outputs):
        if np.ptp(y_test[:, r]) == 0:
            raise IdentificationError(
                f"output {name!r} is constant over the held-out data: the fit is undefined; "
                "use a longer record or a different --train-fraction"
            )
    selection: dict[str, Any] = {"method": "fixed"} if order is not None else {
        "method": "bic", "bic": {str(k): round(v, 3) for k, v in result.bic.items()},
    }
    rows_selection: dict[str, Any] = {"method": "fixed"} if block_rows is not None else {
        "method": "bic", "bic": {str(i): round(r.train_bic, 3) for i, r in results.items()},
    }
    return IdentifiedModel(
        A=result.A, B=result.B, C=result.C, D=result.D, K=result.K,
        Q=result.Q, R=result.R, S=result.S, dt=float(dt), inputs=inputs, outputs=outputs,
        u_offset=u_off, y_offset=y_off,
        fit_pct_per_output=fit_percent(y_test, y_sim[n_train:]),
        singular_values=result.singular_values, block_rows=result.block_rows,
        samples={"total": n_total, "train": n_train, "test": n_test},
        order_selection=selection, block_rows_selection=rows_selection, command=command,
    )


def n4sid(
    u: np.ndarray,
    y: np.ndarray,
    order: int | None = None,
    *,
    max_order: int = DEFAULT_MAX_ORDER,
    block_rows: int | None = None,
    feedthrough: bool = True,
    weighting: str = "n4sid",
    inputs: tuple[str, ...] | None = None,
    outputs: tuple[str, ...] | None = None,
) -> N4sidResult:
    """Identify (A, B, C, D, K, Q, R, S) and the initial state from one record.

    ``order=None`` selects the order (see the module docstring); ``block_rows`` defaults to
    ``DEFAULT_BLOCK_ROWS`` or enough rows for the requested order.
    """
    u2, y2 = _as_2d(u, "u"), _as_2d(y, "y")
    n_samples, m = u2.shape
    ny = y2.shape[1]
    inputs = inputs or tuple(f"u{q}" for q in range(m))
    outputs = outputs or tuple(f"y{r}" for r in range(ny))
    if weighting not in WEIGHTINGS:
        raise IdentificationError(f"weighting must be one of {', '.join(WEIGHTINGS)}")
    if order is not None and order < 1:
        raise IdentificationError(f"order must be >= 1, got {order}")
    if max_order < 1:
        raise IdentificationError(f"max order must be >= 1, got {max_order}")
    i = block_rows if block_rows is not None else default_block_rows(order, ny)
    if i < 2:
        raise IdentificationError(f"block rows must be >= 2, got {i}")
    if order is not None and order > (i - 1) * ny:
        raise IdentificationError(
            f"order {order} needs at least {-(-order // ny) + 1} block rows "
            f"(got {i}); raise --block-rows"
        )
    needed = min_samples(i, m, ny)
    if n_samples < needed:
        raise IdentificationError(
            f"too few samples: {n_samples} for {i} block rows with {m} input(s) and {ny} "
            f"output(s); need at least {needed}. Record longer or lower the block rows"
        )
    _check_data(u2, y2, inputs, outputs)

    su, sy = u2.std(axis=0), y2.std(axis=0)
    us, ys = u2 / su, y2 / sy  # unit variance: the weighting treats every signal alike
    # imported here: every servo process reads model files (this module) and never identifies
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        rows = _HankelRows(_lq_factor(us, ys, i), i, m, ny)
    Oi, P_uf = _oblique(rows.y(i, 2 * i), rows.u(i, 2 * i), rows.past(i))
    Oi_minus, _ = _oblique(rows.y(i + 1, 2 * i), rows.u(i + 1, 2 * i), rows.past(i + 1))
    U_svd, s, W1_inv = _weighted_svd(Oi, P_uf, rows.y(i, 2 * i), weighting)

    def gamma(k: int) -> np.ndarray:
        """Extended observability matrix of order k."""
        g = U_svd[:, :k] * np.sqrt(s[:k])
        return W1_inv @ g if W1_inv is not None else g

    def bic_of(k: int, mse: float) -> float:
        """BIC = N log(V) + p log(N) of an order-k model with simulation error V."""
        n_eff = n_samples * ny
        params = k * (ny + m) + (ny * m if feedthrough else 0) + k
        return n_eff * math.log(max(mse, _ERROR_FLOOR)) + params * math.log(n_eff)

    if order is None:
        nonzero = max(1, int(np.sum(s > _RANK_RTOL * s[0])))
        candidates = range(1, min(max_order, (i - 1) * ny, nonzero) + 1)
        fits = {k: _fit_abd(gamma(k), us, ys, ny, feedthrough) for k in candidates}
        bic = {k: bic_of(k, fitted[-1]) for k, fitted in fits.items()}
        order = min(bic, key=bic.__getitem__)
        A, C, Bs, Ds, x0, _ = fits[order]
        train_bic = bic[order]
    else:
        bic = {}
        A, C, Bs, Ds, x0, mse = _fit_abd(gamma(order), us, ys, ny, feedthrough)
        train_bic = bic_of(order, mse)

    # Noise: residuals of the Kalman state sequences X_i = Gamma^+ O_i, X_i+1 = Gamma_-^+ O_i-1
    # (in LQ coordinates, where a row sequence's Gram matrix is the sample covariance).
    G = gamma(order)
    Xi = np.linalg.pinv(G) @ Oi
    Xi_next = np.linalg.pinv(G[:-ny]) @ Oi_minus
    w_res = Xi_next - A @ Xi - Bs @ rows.u(i, i + 1)
    v_res = rows.y(i, i + 1) - C @ Xi - Ds @ rows.u(i, i + 1)
    Qs, Ss, Rs = w_res @ w_res.T, w_res @ v_res.T, v_res @ v_res.T
    Ks = _kalman_gain(A, C, Qs, Rs, Ss)

    return N4sidResult(
        A=A,
        B=Bs / su,
        C=C * sy[:, None],
        D=Ds * sy[:, None] / su,
        K=Ks / sy,
        Q=Qs,
        R=Rs * np.outer(sy, sy),
        S=Ss * sy,
        x0=x0,
        singular_values=s,
        block_rows=i,
        train_bic=train_bic,
        bic=bic,
    )


def min_samples(block_rows: int, n_inputs: int, n_outputs: int) -> int:
    """Shortest record for ``block_rows``: as many Hankel columns as Hankel rows."""
    return 2 * block_rows * (1 + n_inputs + n_outputs) - 1


def _block_row_candidates(order: int | None, n_outputs: int) -> tuple[int, ...]:
    """``BLOCK_ROW_CANDIDATES``, each raised to what ``order`` needs, ascending."""
    least = default_block_rows(order, n_outputs)
    return tuple(sorted({max(i, least) for i in BLOCK_ROW_CANDIDATES}))


def default_block_rows(order: int | None, n_outputs: int = 1) -> int:
    """``DEFAULT_BLOCK_ROWS``, or more when ``order`` needs them ((i - 1) ny >= order)."""
    needed = -(-order // n_outputs) + 1 if order else 0
    return max(DEFAULT_BLOCK_ROWS, needed)


def simulate(
    A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, u: np.ndarray,
    x0: np.ndarray | None = None,
) -> np.ndarray:
    """Output of x(k+1) = A x + B u, y = C x + D u from ``x0`` (zero by default).

    Computed as D u + (Markov parameters * u) by FFT convolution plus the free response, the
    Markov parameters C A^k coming from repeated squaring: no Python loop over samples.
    """
    u2 = _as_2d(u, "u")
    n_samples = u2.shape[0]
    obs = _observability_sequence(A, C, n_samples)  # (N, ny, n)
    y = u2 @ D.T
    if n_samples > 1 and A.shape[0] > 0:
        markov = obs[: n_samples - 1] @ B  # (N-1, ny, m): C A^k B
        y[1:] += _causal_convolution(markov, u2[:, None, :], n_samples - 1).sum(axis=2)
    if x0 is not None:
        y += obs @ np.asarray(x0, dtype=float)
    if not np.all(np.isfinite(y)):
        raise IdentificationError("simulation diverged: the model is unstable")
    return y


def markov_parameters(
    A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, count: int
) -> np.ndarray:
    """Impulse response [D, CB, CAB, ...]: array (count, outputs, inputs)."""
    out = np.empty((count, C.shape[0], B.shape[1]))
    out[0] = D
    if count > 1:
        out[1:] = _observability_sequence(A, C, count - 1) @ B
    return out


def fit_percent(y: np.ndarray, y_hat: np.ndarray) -> np.ndarray:
    """Per-output fit 100 (1 - ||y - y_hat|| / ||y - mean(y)||)."""
    y2, y_hat2 = _as_2d(y, "y"), _as_2d(y_hat, "y_hat")
    spread = np.linalg.norm(y2 - y2.mean(axis=0), axis=0)
    return 100.0 * (1.0 - np.linalg.norm(y2 - y_hat2, axis=0) / spread)


# -- internals ----------------------------------------------------------------------------


def _as_2d(x: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2:
        raise IdentificationError(f"{name} must be samples x signals, got shape {a.shape}")
    return a


def _check_data(
    u: np.ndarray, y: np.ndarray, inputs: tuple[str, ...], outputs: tuple[str, ...],
    where: str = "",
) -> None:
    if u.shape[0] != y.shape[0]:
        raise IdentificationError(
            f"inputs have {u.shape[0]} samples but outputs {y.shape[0]}: align them first"
        )
    if u.shape[1] == 0 or y.shape[1] == 0:
        raise IdentificationError("at least one input and one output are required")
    for data, names, kind in ((u, inputs, "input"), (y, outputs, "output")):
        for col, name in enumerate(names):
            bad = np.flatnonzero(~np.isfinite(data[:, col]))
            if bad.size:
                raise IdentificationError(
                    f"{kind} {name!r} has {bad.size} NaN/infinite sample(s){where}, first at "
                    f"index {bad[0]}"
                )
            if np.ptp(data[:, col]) == 0:
                hint = "the experiment must switch it" if kind == "input" else "nothing moved"
                raise IdentificationError(
                    f"{kind} {name!r} is constant ({data[0, col]:g}){where}: nothing to identify "
                    f"from; {hint}"
                )


def _lq_factor(us: np.ndarray, ys: np.ndarray, i: int) -> np.ndarray:
    """L of [U_0|2i-1; Y_0|2i-1] / sqrt(j) = L Q^T, built from column chunks (TSQR).

    Called with BLAS limited to one thread: these QRs are tall and thin, and on the shared
    2-core machine OpenBLAS's second thread made them 2x slower when the other core was busy
    and up to 30x slower (17 s instead of 0.6 s for 60 block rows) under a heavier load.
    """
    n_samples, m = us.shape
    ny = ys.shape[1]
    cols = n_samples - 2 * i + 1
    width = 2 * i * (m + ny)
    R = np.zeros((0, width))
    for start in range(0, cols, _QR_CHUNK):
        stop = min(cols, start + _QR_CHUNK)
        seg_u = np.lib.stride_tricks.sliding_window_view(us[start:stop + 2 * i - 1], 2 * i, axis=0)
        seg_y = np.lib.stride_tricks.sliding_window_view(ys[start:stop + 2 * i - 1], 2 * i, axis=0)
        block = np.hstack([
            seg_u.transpose(0, 2, 1).reshape(stop - start, 2 * i * m),
            seg_y.transpose(0, 2, 1).reshape(stop - start, 2 * i * ny),
        ])
        R = np.asarray(np.linalg.qr(np.vstack([R, block]), mode="r"))
    return R.T / math.sqrt(cols)


@dataclass(frozen=True)
class _HankelRows:
    """Row blocks of the LQ factor: inputs u_a..u_b-1 and outputs y_a..y_b-1 of each column."""

    L: np.ndarray
    i: int
    m: int
    ny: int

    def u(self, a: int, b: int) -> np.ndarray:
        return self.L[a * self.m:b * self.m]

    def y(self, a: int, b: int) -> np.ndarray:
        offset = 2 * self.i * self.m
        return self.L[offset + a * self.ny:offset + b * self.ny]

    def past(self, k: int) -> np.ndarray:
        """W_p: inputs and outputs 0..k-1."""
        return np.vstack([self.u(0, k), self.y(0, k)])


def _oblique(
    L_a: np.ndarray, L_b: np.ndarray, L_c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A /_B C (oblique projection of the rows of A along B onto C) in LQ coordinates.

    Returns it with the projector onto the orthogonal complement of the row space of B.
    """
    P_perp = np.eye(L_b.shape[1]) - np.linalg.pinv(L_b, rcond=_RANK_RTOL) @ L_b
    C_perp = L_c @ P_perp
    return L_a @ P_perp @ np.linalg.pinv(C_perp, rcond=_RANK_RTOL) @ L_c, P_perp


def _weighted_svd(
    Oi: np.ndarray, P_uf: np.ndarray, Yf: np.ndarray, weighting: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Left singular vectors and singular values of W1 O_i W2, and W1^-1 (None for W1 = I)."""
    if weighting == "n4sid":
        weighted, W1_inv = Oi, None
    elif weighting == "moesp":
        weighted, W1_inv = Oi @ P_uf, None
    else:  # cva: W1 = (Yf Pi_Uf^perp Yf^T)^(-1/2), W2 = Pi_Uf^perp
        yf_perp = Yf @ P_uf
        w, V = np.linalg.eigh(yf_perp @ yf_perp.T)
        w = np.maximum(w, _RANK_RTOL * max(w.max(), 1e-300))
        W1_inv = (V * np.sqrt(w)) @ V.T
        weighted = ((V / np.sqrt(w)) @ V.T) @ Oi @ P_uf
    U_svd, s, _ = np.linalg.svd(weighted, full_matrices=False)
    return U_svd, s, W1_inv


def _fit_abd(
    G: np.ndarray, us: np.ndarray, ys: np.ndarray, ny: int, feedthrough: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """A, C from the observability matrix; B, D, x0 by least squares on the simulation error.

    Returns (A, C, B, D, x0, mean squared simulation error), in scaled units.
    """
    n = G.shape[1]
    m = us.shape[1]
    C = G[:ny]
    A = _stabilize(np.linalg.lstsq(G[:-ny], G[ny:], rcond=None)[0])
    n_samples = us.shape[0]
    obs = _observability_sequence(A, C, n_samples)  # (N, ny, n)
    regressors = [obs.reshape(n_samples * ny, n)]
    forced = np.zeros((n_samples, ny, n, m))
    if n_samples > 1:
        forced[1:] = _causal_convolution(
            obs[: n_samples - 1, :, :, None], us[:, None, None, :], n_samples - 1
        )
    regressors.append(forced.reshape(n_samples * ny, n * m))
    if feedthrough:
        direct = np.zeros((n_samples, ny, ny, m))
        for r in range(ny):
            direct[:, r, r, :] = us
        regressors.append(direct.reshape(n_samples * ny, ny * m))
    phi = np.hstack(regressors)
    target = ys.reshape(-1)
    theta = np.linalg.lstsq(phi, target, rcond=None)[0]
    mse = float(np.mean((target - phi @ theta) ** 2))
    x0 = theta[:n]
    B = theta[n:n + n * m].reshape(n, m)
    D = theta[n + n * m:].reshape(ny, m) if feedthrough else np.zeros((ny, m))
    return A, C, B, D, x0, mse


def _causal_convolution(h: np.ndarray, x: np.ndarray, count: int) -> np.ndarray:
    """First ``count`` samples of the convolution of ``h`` and ``x`` along axis 0 (by FFT)."""
    size = 1 << (2 * count - 2).bit_length()  # >= 2 count - 1: no circular wrap-around
    spectrum = np.fft.rfft(h[:count], size, axis=0) * np.fft.rfft(x[:count], size, axis=0)
    return np.fft.irfft(spectrum, size, axis=0)[:count]


def _observability_sequence(A: np.ndarray, C: np.ndarray, count: int) -> np.ndarray:
    """[C, CA, CA^2, ...] as an array (count, ny, n), by repeated squaring of A."""
    blocks = C[None, :, :]
    power = A
    while blocks.shape[0] < count:
        blocks = np.concatenate([blocks, blocks @ power])
        power = power @ power
    return blocks[:count]


def _stabilize(A: np.ndarray) -> np.ndarray:
    """Reflect eigenvalues outside the unit circle to 1 / conj(lambda)."""
    lam, V = np.linalg.eig(A)
    outside = np.abs(lam) > 1.0
    if not outside.any():
        return A
    lam = np.where(outside, lam / np.abs(lam) ** 2, lam)
    return np.real(V @ np.diag(lam) @ np.linalg.inv(V))


def _kalman_gain(
    A: np.ndarray, C: np.ndarray, Q: np.ndarray, R: np.ndarray, S: np.ndarray
) -> np.ndarray:
    """Steady-state Kalman gain of the innovation form (scaled units, R relative to 1)."""
    ny = C.shape[0]
    R_reg = R + _RANK_RTOL * np.eye(ny)  # noise-free data: R = 0 would make the gain undefined
    from scipy import linalg  # here: scipy.linalg is a fifth of a second of every process start

    try:
        P = linalg.solve_discrete_are(A.T, C.T, Q, R_reg, s=S)
    except (np.linalg.LinAlgError, ValueError):
        P = Q.copy()  # Riccati recursion from P = Q when the pencil solver gives up
        for _ in range(2000):
            gain = (A @ P @ C.T + S) @ np.linalg.inv(C @ P @ C.T + R_reg)
            P_next = A @ P @ A.T + Q - gain @ (A @ P @ C.T + S).T
            if np.allclose(P_next, P, rtol=1e-12, atol=1e-14):
                break
            P = P_next
    return (A @ P @ C.T + S) @ np.linalg.inv(C @ P @ C.T + R_reg)
