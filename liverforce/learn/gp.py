"""The Gaussian-process force regressor (``model.regressor: gp``).

An exact GP per force component with one kernel shared by the three
components (the standardised local force ``(F.t1, F.t2, F.n)``), or with
``model.gp.per_output: true`` one kernel per component (own length scales and
variances, each by its own marginal likelihood)::

    k(z, z') = s_f^2 (1 + r^2 / (2 a))^-a + s_l^2 z . z',   r = |(z - z') / l|   (ARD length scales l, one per input)
    f(z)     = k(z, Z) alpha,   alpha = (K + s_n^2 I)^-1 Y

The first term is the rational-quadratic kernel (``model.gp.kernel: rational_quadratic``, the
default): a scale mixture of squared exponentials of shape ``a`` (``model.gp.shape``: 2, or null
to fit it with the rest). Its tails are heavier than the squared exponential's (``exp(-r^2 / 2)``,
the limit ``a -> infinity``; ``model.gp.kernel: squared_exponential``), so a case farther from the
training rows than they are from each other (a liver at the population's edge) keeps more of the
fitted correction instead of falling back to the linear term. On scenario IV's training livers (5
splits x 4 folds by liver, pca_sv, ``benchmarks/experiment_gp_kernel.py``) it lowered the CV MAE
by 5 % (0.1668 -> 0.1583 N).

``l``, ``s_f``, ``s_l``, ``s_n`` (and ``a`` when it is not fixed) maximise the marginal likelihood of the
training rows (summed over the components; one row per case when a case is seen
through several noisy views, see :func:`fit_gp`), by L-BFGS in torch (float64). The
inputs are the regressor inputs of :mod:`liverforce.learn.model` (standardised
code, state vector and linear force estimate), so one length scale per input
learns which of them matter; the linear term carries the near-linear part of
the force-displacement map, the stationary term its smooth nonlinear
correction. Nothing but the kernel's family and shape (chosen once by training-side
CV) is set by hand (no Ax search): the other hyper-parameters are the likelihood's.

Why a GP and not only the MLP: the data are few hundred noise-free FE cases
per scenario. ``benchmarks/experiment_regressor.py`` measures both on the same
seeded splits (scenario-IV test livers and the unseen livers) and also
BoTorch's ``SingleTaskGP`` on the same inputs as a peer.

An exact GP costs ``O(n^3)`` per likelihood evaluation: above ``max_points``
training rows a seeded subset of that size is used (recorded in the bundle).
The fitted regressor is a :class:`torch.nn.Module` whose state is buffers only
(training inputs, ``alpha``, hyper-parameters), saved and loaded with the
model bundle like the MLP's weights.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import nn

from liverforce.learn import names
from liverforce.seeds import derive

POW_SHAPE_MAX = 64.0  # integer rational-quadratic shapes up to this are evaluated as pow(B, -a) (neg_log_likelihood)
POW_SHAPE_MAX_HEAD = 4  # and up to this as 1 / B^a by products in the NumPy head (GPRegressor.numpy_head): a
#                        relative rounding of about a eps, where exp(-a log1p(t)) has 1-2 ulp; a = 2 (the default)
#                        costs one product and a reciprocal per kernel value instead of log1p and exp
JITTER = 1e-6  # added to the noise variance: keeps K + s_n^2 I positive definite for noise-free FE targets
MIN_LENGTH = 1.0  # shortest length scale, in standard deviations of the (standardised) input. Without it the
#                 likelihood can send one input's length scale to zero: the kernel becomes the identity and the GP
#                 interpolates noisy (camera) features exactly while predicting the mean elsewhere (seen on one
#                 scenario-III cloud split: train MSE 1e-10, test MSE 0.9 of the variance). Healthy fits on the
#                 default data stay above 2.


class GPRegressor(nn.Module):
    """Posterior mean of a fitted GP (module docstring); every state tensor is a float64 buffer."""

    def __init__(self, X: torch.Tensor, alpha: torch.Tensor, inv_length: torch.Tensor,
                 signal_var: torch.Tensor, linear_var: torch.Tensor, noise_var: torch.Tensor,
                 shape: torch.Tensor | float = math.inf):
        super().__init__()
        self.register_buffer("X", X.double().contiguous())
        self.register_buffer("alpha", alpha.double().contiguous())
        inv_length = inv_length.double().contiguous()
        if inv_length.ndim not in (1, 2) or (inv_length.ndim == 2 and inv_length.shape[0] != self.alpha.shape[1]):
            raise ValueError(f"GPRegressor: inverse length scales (inputs,) or (outputs, inputs); got "
                             f"{tuple(inv_length.shape)} for {self.alpha.shape[1]} outputs")
        # per output (model.gp.per_output): one row of length scales, and one of each variance, per output
        var_shape = (inv_length.shape[0],) if inv_length.ndim == 2 else ()
        self.register_buffer("inv_length", inv_length)
        self.register_buffer("signal_var", signal_var.double().reshape(var_shape))
        self.register_buffer("linear_var", linear_var.double().reshape(var_shape))
        self.register_buffer("noise_var", noise_var.double().reshape(var_shape))
        # the rational-quadratic shape a; inf: the squared exponential (bundles written before the
        # kernel was a choice have no such buffer and are squared-exponential GPs)
        self.register_buffer("shape", torch.as_tensor(shape, dtype=torch.float64).reshape(()))
        if not float(self.shape) > 0:
            raise ValueError(f"GPRegressor: the kernel shape must be positive (inf: squared exponential); "
                             f"got {float(self.shape)}")

    @classmethod
    def from_state_dict(cls, state: dict) -> "GPRegressor":
        return cls(*(state[k] for k in ("X", "alpha", "inv_length", "signal_var", "linear_var", "noise_var")),
                   shape=state.get("shape", math.inf))

    @property
    def kernel(self) -> str:
        return "squared_exponential" if math.isinf(float(self.shape)) else "rational_quadratic"

    @property
    def n_train(self) -> int:
        return int(self.X.shape[0])

    @property
    def per_output(self) -> bool:
        """Whether each output has its own kernel (``model.gp.per_output``)."""
        return self.inv_length.ndim == 2

    def output(self, k: int) -> "GPRegressor":
        """Output ``k`` of a per-output GP as a GP of its own (one output; the buffers are views)."""
        return GPRegressor(self.X, self.alpha[:, k:k + 1], self.inv_length[k], self.signal_var[k],
                           self.linear_var[k], self.noise_var[k], self.shape)

    def nearest_distance(self, z, groups=None, row_groups=None) -> np.ndarray:
        """``(n,)``: each row of ``z`` ``(n, d)``'s distance to the nearest training row, in inputs scaled by the
        inverse length scales (the kernel's ``r``); a per-output GP's mean over its outputs. How far a case lies
        from every case the GP learned from (:func:`nearest_scaled`), the input distance a prediction is flagged
        by (:mod:`liverforce.learn.interval`). ``groups`` ``(n,)`` and ``row_groups`` (one label per training
        row): a training row with the case's own label is left out (the training side's distances)."""
        z = np.asarray(z, dtype=np.float64)
        X = self.X.numpy()
        il = self.inv_length.numpy()
        rows = il if self.per_output else il[None]
        return np.mean([nearest_scaled(z * r, X * r, groups_a=groups, groups_b=row_groups) for r in rows], axis=0)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        z = z.double()
        if self.per_output:
            return torch.cat([_kernel(z, self.X, self.inv_length[k], self.signal_var[k], self.linear_var[k],
                                      float(self.shape)) @ self.alpha[:, k:k + 1]
                              for k in range(self.alpha.shape[1])], 1)
        return _kernel(z, self.X, self.inv_length, self.signal_var, self.linear_var, float(self.shape)) @ self.alpha

    def numpy_head(self, fixed: dict | None = None, distance: bool = False):
        """A float64 NumPy function ``Z (n, d) -> scaled outputs (n, 3)`` (the compiled serving paths).

        The same posterior mean as :meth:`forward` in fewer passes over the (rows x training rows)
        matrix: ``-d2 / 2 = z_s . x_s - (|z_s|^2 + |x_s|^2) / 2`` (``_s``: scaled by the inverse length
        scales; not clamped at 0 as the module clamps ``d2``: where it rounds above 0, by ~1e-13 near a
        training input, the kernel is 1 + 1e-13) as one BLAS product of ``[z_s, -|z_s|^2 / 2, 1]`` and
        ``[x_s, 1, -|x_s|^2 / 2]``,
        ``s_f^2`` folded into ``alpha`` and the linear term into one (d, 3) matrix ``s_l^2 X^T alpha``: one
        BLAS product, ``exp`` and two products with 3 columns. The rational quadratic is
        ``exp(-a log1p(d2 / (2 a)))``: one ``log1p`` more; for a whole ``a`` up to
        :data:`POW_SHAPE_MAX_HEAD` (the default 2) ``1 / (1 + d2 / (2 a))^a`` by products, no ``exp``, in one
        compiled pass with the product by ``alpha`` (:func:`_rq_power_mean`).

        ``fixed``: ``{input column: value}`` for inputs that are the same in every row (a compiled
        context's state vector). The head then takes only the other columns, in their order; the fixed
        inputs' part of each training row's distance (``|v_s - x_s|^2``, computed directly) and of the
        linear term is computed here, once.

        A per-output GP (``model.gp.per_output``) runs one such head per output, each on its own length
        scales, and returns their columns side by side.

        ``distance``: the head returns ``(outputs, distances (n,))``, the distances of :meth:`nearest_distance`
        read off the same matrix (``d2 = -2 max_j E_ij``: one pass more over it, no other product).
        """
        if self.per_output:
            heads = [self.output(k).numpy_head(fixed, distance) for k in range(self.alpha.shape[1])]

            def head_per_output(Z: np.ndarray):
                if not distance:
                    return np.concatenate([h(Z) for h in heads], axis=1)
                got = [h(Z) for h in heads]
                return np.concatenate([g[0] for g in got], axis=1), np.mean([g[1] for g in got], axis=0)

            return head_per_output
        Xs = (self.X * self.inv_length).numpy()
        d_all = Xs.shape[1]
        fixed = _fixed_inputs(fixed, d_all)
        fc = np.array(sorted(fixed), dtype=np.int64)
        fv = np.array([fixed[c] for c in fc])  # their values
        fr = np.array([c for c in range(d_all) if c not in fixed], dtype=np.int64)
        d = fr.size
        inv_l_all = self.inv_length.numpy()
        XaT = np.empty((d + 2, Xs.shape[0]))  # [x_s, 1, -(|x_s|^2 + |x_s - v_s|^2 over the fixed inputs) / 2]^T
        XaT[:d] = Xs[:, fr].T
        XaT[d] = 1.0
        XaT[d + 1] = -0.5 * np.einsum("ij,ij->i", XaT[:d].T, XaT[:d].T)
        if fc.size:
            gap = Xs[:, fc] - fv * inv_l_all[fc]
            XaT[d + 1] -= 0.5 * np.einsum("ij,ij->i", gap, gap)
        inv_l = inv_l_all[fr].copy()
        alpha = self.alpha.numpy()
        alpha_s = float(self.signal_var) * alpha
        alpha_sT = np.ascontiguousarray(alpha_s.T)  # (3, n_train): _rq_power_mean reads each output's row
        beta_all = float(self.linear_var) * (self.X.numpy().T @ alpha)
        beta = np.ascontiguousarray(beta_all[fr])
        b0 = fv @ beta_all[fc] if fc.size else None  # the fixed inputs' linear term
        a = float(self.shape)
        rq = not math.isinf(a)
        power = int(a) if rq and a == int(a) and a <= POW_SHAPE_MAX_HEAD else 0  # B^-a by products, 1 / B^a

        def head(Z: np.ndarray) -> np.ndarray:
            Z = np.asarray(Z, dtype=np.float64)
            if Z.ndim != 2 or Z.shape[1] != d:
                raise ValueError(f"the GP head takes rows of {d} inputs, got an array of shape {Z.shape}")
            Za = np.empty((len(Z), d + 2))  # [z_s, -|z_s|^2 / 2, 1]
            Zs = Za[:, :d]
            np.multiply(Z, inv_l, out=Zs)
            Za[:, d] = -0.5 * np.einsum("ij,ij->i", Zs, Zs)
            Za[:, d + 1] = 1.0
            E = Za @ XaT  # -d2 / 2, not clamped at 0: where it rounds above 0 (~1e-13) the kernel is 1 + 1e-13
            near = np.sqrt(np.maximum(-2.0 * E.max(axis=1), 0.0)) if distance else None  # before E is reused
            if power:  # a small whole a: (1 + d2 / (2 a))^-a = 1 / B^a, B = 1 - E / a, no exp or log1p, and the
                # product with alpha in the same pass over E (_rq_power_mean)
                out = Z @ beta
                _rq_power_mean(E, 1.0 / a, power, alpha_sT, out)
                if b0 is not None:
                    out += b0
                return (out, near) if distance else out
            # exp and log1p in place, with the faster of NumPy and torch on this CPU (_exp_, _log1p_)
            if rq:  # (1 + d2 / (2 a))^-a = exp(-a log1p(-E / a))
                E *= -1.0 / a
                _log1p_(E)
                E *= -a
            _exp_(E)
            out = E @ alpha_s + Z @ beta
            if b0 is not None:
                out += b0
            return (out, near) if distance else out

        if power:  # load (or compile) the fused pass now, with the signature of every call, not on the first row
            m = alpha_sT.shape[0]  # a compiled path serves (CompiledROI, CompiledCloud)
            _rq_power_mean(np.zeros((1, 1)), 1.0, power, np.zeros((m, 1)), np.zeros((1, m)))
        return head


KERNELS = names.GP_KERNELS


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "nsz", "contract", "arcp"})
def _rq_power_mean(E, inv_a, power, alphaT, out):
    """``out[i] += sum_j B_ij^-power alphaT[:, j]``, ``B = 1 - E inv_a``: the rational quadratic of a whole shape
    ``a = power`` (1 to :data:`POW_SHAPE_MAX_HEAD`) and its product with the (m, n) weights in one pass over
    ``E`` (``-d2 / 2``, rows x training rows) for the shipped a = 2 and three outputs (one pass per output
    otherwise: a per-output GP's heads have one each), where NumPy makes five (scale, shift, power, reciprocal,
    product).
    The NumPy error model lets LLVM vectorise the division (Python's raises on a zero divisor: a branch per
    value; ``B >= 1`` here up to rounding), and the fast-math flags the sums; their order depends on the row
    alone, so a row gives the same bits alone and in a batch (``benchmarks/bench_gp_head.py`` times both)."""
    n, N = E.shape
    m = alphaT.shape[0]
    nn_ = np.uint64(N)
    for i in range(n):
        e = E[i]
        if m == 3 and power == 2:  # the default shape and outputs: one loop for the three, which LLVM vectorises
            a0, a1, a2 = alphaT[0], alphaT[1], alphaT[2]
            o0 = 0.0
            o1 = 0.0
            o2 = 0.0
            for j in range(nn_):
                b = 1.0 - e[j] * inv_a
                k = 1.0 / (b * b)
                o0 += k * a0[j]
                o1 += k * a1[j]
                o2 += k * a2[j]
            out[i, 0] += o0
            out[i, 1] += o1
            out[i, 2] += o2
        else:
            for c in range(m):
                ac = alphaT[c]
                o = 0.0
                for j in range(nn_):
                    b = 1.0 - e[j] * inv_a
                    bp = b
                    for _ in range(power - 1):
                        bp *= b
                    o += ac[j] / bp
                out[i, c] += o


def _numpy_avx512(ufunc: str) -> bool:
    """Whether NumPy's float64 ``ufunc`` runs its AVX-512 kernel on this CPU (``numpy.lib.introspect``, NumPy 2)."""
    try:
        current = np.lib.introspect.opt_func_info(func_name=f"^{ufunc}$")[ufunc]["dd"]["current"]
    except (AttributeError, KeyError, TypeError):
        return False
    return current == "X86_V4" or "AVX512" in current


def _in_place(ufunc: str, use_numpy: bool):
    """``f(E)``: ``E[:] = ufunc(E)`` for a float64 array, by NumPy or by torch (``_exp_``, ``_log1p_``: NumPy where
    its kernel is AVX-512, else torch).

    The GP head's exp (and the rational quadratic's log1p) over rows x training rows. NumPy's float64 exp
    and log1p are vectorised only with AVX-512; torch's (SLEEF, 1 ulp) with AVX2 too. Per value, 128 x 2,000
    values, 1 thread (medians of 300): on an AVX2 host torch's exp was 3x NumPy's speed (session 36); on an
    AVX-512 host (AMD EPYC) NumPy's exp 0.82 ns against torch's 1.60, log1p 1.23 against 2.00. Both agree to
    1 ulp, so the choice moves a force by rounding only; it is fixed per host, so the same host gives the same
    bits."""
    if use_numpy:
        f = getattr(np, ufunc)
        return lambda E: f(E, out=E)
    method = getattr(torch.Tensor, ufunc + "_")  # looked up once, not per call
    return lambda E: method(torch.from_numpy(E))


_exp_ = _in_place("exp", _numpy_avx512("exp"))
_log1p_ = _in_place("log1p", _numpy_avx512("log1p"))


def _fixed_inputs(fixed: dict | None, n_in: int) -> dict:
    """``numpy_head``'s ``fixed`` checked: whole input columns in ``[0, n_in)``, finite values."""
    out = {}
    for c, v in (fixed or {}).items():
        if isinstance(c, bool) or not float(c).is_integer() or not 0 <= int(c) < n_in:
            raise ValueError(f"numpy_head: fixed columns must index the {n_in} inputs; got {c!r}")
        if not math.isfinite(float(v)):
            raise ValueError(f"numpy_head: the fixed input {int(c)} must be finite; got {v!r}")
        out[int(c)] = float(v)
    return out


def training_rows(n: int, seed: int, max_points: int) -> np.ndarray:
    """The rows of ``n`` training rows that :func:`fit_gp` keeps (sorted): all of them, or above ``max_points`` a
    subset of that size drawn with ``seed``."""
    if n <= int(max_points):
        return np.arange(n)
    rng = np.random.default_rng(derive(seed, "gp.subset"))
    return np.sort(rng.choice(n, size=int(max_points), replace=False))


def nearest_scaled(A: np.ndarray, B: np.ndarray, block: int = 1024, groups_a=None, groups_b=None) -> np.ndarray:
    """``(len(A),)``: each row of ``A``'s Euclidean distance to the nearest row of ``B`` (float64, in blocks of
    ``block`` rows of ``A``: the ``(block, len(B))`` matrix at a time). ``groups_a`` ``(len(A),)`` and ``groups_b``
    ``(len(B),)``: labels; a row of ``B`` with the label of the row of ``A`` is left out (its own liver; inf when
    every row is)."""
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    if (groups_a is None) != (groups_b is None):
        raise ValueError("nearest_scaled: give the labels of both A's and B's rows, or of neither")
    bb = np.einsum("ij,ij->i", B, B)
    out = np.empty(len(A))
    for a in range(0, len(A), block):
        P = A[a:a + block]
        d2 = np.einsum("ij,ij->i", P, P)[:, None] + bb[None] - 2.0 * (P @ B.T)
        if groups_a is not None:
            d2[np.asarray(groups_a)[a:a + block, None] == np.asarray(groups_b)[None, :]] = np.inf
        out[a:a + block] = np.sqrt(np.maximum(d2.min(axis=1), 0.0))
    return out


def _sq_dist(a, b):
    """``|a_i - b_j|^2`` of inputs already divided by the length scales."""
    return ((a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * (a @ b.T)).clamp_min(0.0)


def _shape_kernel(d2, shape):
    """The stationary part of the kernel without ``s_f^2``: ``(1 + d2 / (2 a))^-a``, ``exp(-d2 / 2)`` at ``a = inf``
    (``shape`` a float, or a tensor to differentiate through)."""
    if not torch.is_tensor(shape) and math.isinf(shape):
        return torch.exp(-0.5 * d2)
    return torch.exp(-shape * torch.log1p(d2 / (2.0 * shape)))


def _kernel(A, B, inv_length, signal_var, linear_var, shape: float = math.inf):
    return signal_var * _shape_kernel(_sq_dist(A * inv_length, B * inv_length), shape) + linear_var * (A @ B.T)


def neg_log_likelihood(X: torch.Tensor, Y: torch.Tensor, log_l: torch.Tensor, log_sf: torch.Tensor,
                       log_sl: torch.Tensor, log_sn: torch.Tensor, log_a: torch.Tensor | None = None, *,
                       gradient: bool = True, shape_gradient: bool = True, noise_floor: float = 0.0):
    """Negative log marginal likelihood per row and output of ``Y (n, m)`` given ``X (n, d)``, its gradient
    with respect to ``(log_l, log_sf, log_sl, log_sn[, log_a])`` (raw parameters of :func:`fit_gp`: ``l =
    MIN_LENGTH + exp(log_l)``, variances ``exp(2 log_s)``, the rational-quadratic shape ``a = exp(log_a)``;
    ``log_a`` None: the squared exponential) and ``alpha = K^-1 Y``; None where ``K`` is not positive definite.
    ``noise_floor``: a fixed variance added to the fitted noise variance ``exp(2 log_sn)`` (:func:`fit_gp`).
    ``shape_gradient=False``: the shape is fixed, its derivative is not computed (four gradients).

    The gradient is the closed form (Rasmussen & Williams 2006, eq. 5.9) summed over the outputs::

        dv/dt = tr(W dK/dt) / (2 n m),   W = m K^-1 - alpha alpha^T

    with the length-scale derivative reduced to ``(d,)`` sums over ``M = W o dk/d(d2)``:
    ``sum_ij M_ij (x_id - x_jd)^2 = 2 (x_d^2 . M 1 - x_d . M x_d)``. ``-2 dk/d(d2)`` is ``E = exp(-d2 / 2)``
    for the squared exponential and ``B^(-a-1)``, ``B = 1 + d2 / (2 a)``, for the rational quadratic,
    whose shape derivative is ``a dP/da = a P (1 - 1/B - log B)``, ``P = B^-a``. One Cholesky factor and
    one inverse per evaluation: about a third of the time autograd's backward pass through the
    factorisation takes.
    """
    n, m = Y.shape
    ls = MIN_LENGTH + torch.exp(log_l)
    sf2, sl2, sn2 = torch.exp(2 * log_sf), torch.exp(2 * log_sl), torch.exp(2 * log_sn)
    d2 = _sq_dist(X / ls, X / ls)
    if log_a is None:
        P = torch.exp(-0.5 * d2)
    else:
        a = float(torch.exp(log_a))
        t = d2 / (2.0 * a)
        B = 1.0 + t
        # B^-a: torch's pow has fast paths for small integer exponents (a = 2: 5x faster than exp(-a log1p(t)));
        # rounding B costs a relative a * eps, so a large or fractional a goes through log1p
        fast = a <= POW_SHAPE_MAX and a == int(a)
        logB = None if fast else torch.log1p(t)
        P = torch.pow(B, -a) if fast else torch.exp(-a * logB)
    XX = X @ X.T
    K = sf2 * P + sl2 * XX
    K.diagonal().add_(sn2 + JITTER + noise_floor)
    L, info = torch.linalg.cholesky_ex(K)
    if int(info) != 0:
        return None
    alpha = torch.cholesky_solve(Y, L)
    v = float(0.5 * (Y * alpha).sum() + m * torch.log(torch.diagonal(L)).sum()) / (n * m) + 0.5 * math.log(2 * math.pi)
    if not gradient:
        return v, None, alpha
    W = torch.cholesky_inverse(L)
    W.mul_(m).sub_(alpha @ alpha.T)
    c = 0.5 / (n * m)
    WP = W * P
    g_sf = c * 2.0 * sf2 * WP.sum()
    g_sl = c * 2.0 * sl2 * (W * XX).sum()
    g_sn = c * 2.0 * sn2 * torch.diagonal(W).sum()
    M = WP if log_a is None else WP / B  # W o B^(-a-1) for the rational quadratic
    sums = 2.0 * ((X * X).T @ M.sum(1) - (X * (M @ X)).sum(0))  # sum_ij M_ij (x_id - x_jd)^2, (d,)
    g_l = c * sf2 * sums * (ls - MIN_LENGTH) / ls ** 3
    grads = [g_l, g_sf.reshape(()), g_sl.reshape(()), g_sn.reshape(())]
    if log_a is not None and shape_gradient:  # 1 - 1/B - log B = t/(1+t) - log1p(t): a series where they cancel
        bracket = torch.where(t < 1e-3, t * t * (-0.5 + t * (2.0 / 3.0 - 0.75 * t)),
                              t / B - (torch.log1p(t) if logB is None else logB))
        grads.append((c * sf2 * a * (WP * bracket).sum()).reshape(()))
    return v, grads, alpha


def fit_gp(z: np.ndarray, y: np.ndarray, *, seed: int, max_points: int = 2000,
           iterations: int = 200, groups: np.ndarray | None = None,
           kernel: str = "rational_quadratic", shape: float | None = 2.0,
           per_output: bool = False, noise_floor: float = 0.0) -> tuple[GPRegressor, dict]:
    """Fit the GP of the module docstring to ``z (n, d) -> y (n, k)`` (standardised); returns ``(gp, info)``.

    ``kernel``: ``rational_quadratic`` or ``squared_exponential``. ``shape``: the rational quadratic's
    ``a``, fixed (2, the config's default); None: fitted with the rest by the likelihood (from ``a = 1``).

    ``per_output`` (``model.gp.per_output``): one kernel per output instead of one shared by all: each
    output's length scales and variances maximise its own marginal likelihood (k fits instead of one).
    The tangential force components and the normal one are read from different inputs (a camera model's
    tangential force mostly from the tool's tangential displacement, its normal force from the dent), and a
    shared kernel's length scales are a compromise between them. A fitted shape (``shape`` None) is refused
    with it: the rational quadratic's ``a`` is one number for the whole GP.

    ``groups`` (n,): rows with the same label are views of one case (a camera model sees each training
    case through several seeded noisy observations, all with the case's force). The hyper-parameters
    then maximise the marginal likelihood of one row per case (the first), and only the posterior
    (``alpha``) uses every row. Fitted on all views, the likelihood rewards explaining each case's
    twin views exactly: the noise variance falls to the jitter and the GP interpolates the input noise
    (seen on scenario IV with a tool tip noisy along the normal only: test accuracy 72 % against
    87 % with one row per case; ``tests/learn/test_gp.py`` reproduces it on synthetic data).

    ``noise_floor`` (``model.gp.noise_floor``, in the standardised targets' variance): the noise variance is
    at least this, in the likelihood and in the posterior alike (the fitted variance is added to it). A camera
    model's inputs are noisy while its FE targets are not: on one view per case the likelihood sends the noise
    variance to the jitter, and the posterior over every view then interpolates each case's views, which
    differ only by the observation's noise, exactly (``config/train/default.yaml``, the camera variant).

    ``info``: ``n_used`` (rows after the ``max_points`` cap, a subset drawn with ``seed``),
    ``n_likelihood`` (rows of the likelihood), ``nll`` (negative log marginal likelihood per row and
    output at the optimum), ``length_scales``, ``noise_var`` (the fitted variance + the floor + the jitter, the
    posterior's), ``noise_floor``, ``evaluations``, ``kernel`` and
    ``shape`` (``a``; None for the squared exponential).
    """
    if kernel not in KERNELS:
        raise ValueError(f"model.gp.kernel: unknown '{kernel}', choose one of {', '.join(KERNELS)}")
    if shape is not None and not (math.isfinite(float(shape)) and float(shape) > 0):
        raise ValueError(f"model.gp.shape: the rational quadratic's a must be a positive number, or null to fit it; "
                         f"got {shape}")
    if per_output and kernel == "rational_quadratic" and shape is None:
        raise ValueError("model.gp.per_output: the rational quadratic's shape must be fixed (model.gp.shape a "
                         "number) with one kernel per output; got null (fitted)")
    z = np.asarray(z, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if z.ndim != 2 or y.ndim != 2 or len(z) != len(y):
        raise ValueError(f"fit_gp: expected z (n, d) and y (n, k) with the same n; got {z.shape} and {y.shape}")
    if len(z) < 2:
        raise ValueError(f"need at least 2 training samples, got {len(z)}")
    if not (np.isfinite(z).all() and np.isfinite(y).all()):
        raise ValueError("fit_gp: non-finite training inputs or targets")
    if int(max_points) < 2:
        raise ValueError(f"model.gp.max_points must be at least 2, got {max_points}")
    noise_floor = float(noise_floor)
    if not (math.isfinite(noise_floor) and noise_floor >= 0):
        raise ValueError(f"model.gp.noise_floor must be a finite variance >= 0, got {noise_floor}")
    if groups is not None:
        groups = np.asarray(groups)
        if groups.shape != (len(z),):
            raise ValueError(f"fit_gp: groups must label every row ({len(z)}); got shape {groups.shape}")
        if len(np.unique(groups)) < 2:
            raise ValueError("fit_gp: the groups name a single case; need at least 2 cases")
    rows = training_rows(len(z), seed, max_points)
    X = torch.from_numpy(z[rows])
    Y = torch.from_numpy(y[rows])
    n = X.shape[0]
    Xh, Yh = X, Y
    if groups is not None:  # one row per case for the likelihood: the first of its views among the rows kept
        first = np.sort(np.unique(groups[rows], return_index=True)[1])
        if len(first) < n:
            Xh, Yh = X[first], Y[first]
    # one fit for the shared kernel, or one per output (its own length scales and variances, own likelihood)
    parts = [slice(k, k + 1) for k in range(Y.shape[1])] if per_output else [slice(None)]
    fits = [_fit_hyper(X, Y[:, c], Xh, Yh[:, c], kernel, shape, iterations, noise_floor) for c in parts]
    raw = [torch.stack([f[0][i] for f in fits]) if per_output else fits[0][0][i] for i in range(4)]
    log_a = fits[0][1]
    shape = math.inf if log_a is None else float(shape) if shape is not None else float(torch.exp(log_a))
    gp = GPRegressor(X, torch.cat([f[3] for f in fits], 1), 1.0 / (MIN_LENGTH + torch.exp(raw[0])),
                     torch.exp(2 * raw[1]), torch.exp(2 * raw[2]),
                     torch.exp(2 * raw[3]) + JITTER + noise_floor, shape)
    return gp.eval(), {"n_used": int(n), "n_likelihood": int(len(Xh)),
                       "nll": float(np.mean([f[2] for f in fits])), "evaluations": int(sum(f[4] for f in fits)),
                       "per_output": bool(per_output), "length_scales": (MIN_LENGTH + torch.exp(raw[0])).tolist(),
                       "noise_var": gp.noise_var.tolist(), "noise_floor": noise_floor, "kernel": kernel,
                       "shape": None if math.isinf(shape) else shape}


def _fit_hyper(X, Y, Xh, Yh, kernel: str, shape: float | None, iterations: int, noise_floor: float = 0.0):
    """The hyper-parameters of :func:`fit_gp` for ``Xh -> Yh`` (the likelihood's rows), ``alpha`` over ``X -> Y``
    (the noise variance ``noise_floor`` + the fitted one):
    returns ``(raw (log_l, log_sf, log_sl, log_sn), log_a or None, nll per row and output, alpha, evaluations)``."""
    d = X.shape[1]
    # length scale l = MIN_LENGTH + exp(raw): smooth, and never below MIN_LENGTH
    l0 = max(math.sqrt(d) / 2.0, 2.0 * MIN_LENGTH)
    log_l = torch.full((d,), math.log(l0 - MIN_LENGTH), dtype=torch.float64)
    log_sf = torch.zeros((), dtype=torch.float64)
    log_sl = torch.full((), math.log(0.1), dtype=torch.float64)
    log_sn = torch.full((), math.log(0.1), dtype=torch.float64)
    params = [log_l, log_sf, log_sl, log_sn]
    log_a = None  # the squared exponential
    if kernel == "rational_quadratic":
        log_a = torch.tensor(0.0 if shape is None else math.log(float(shape)), dtype=torch.float64)
        if shape is None:
            params.append(log_a)  # fitted, from a = 1

    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=int(iterations), line_search_fn="strong_wolfe")
    evaluations = [0]
    best = {"v": math.inf, "state": [p.detach().clone() for p in params]}

    def closure():
        evaluations[0] += 1
        got = neg_log_likelihood(Xh, Yh, *params[:4], log_a, gradient=True, shape_gradient=len(params) > 4,
                                 noise_floor=noise_floor)
        if got is None:  # not positive definite at this trial point: make the line search step back
            for p in params:
                p.grad = torch.zeros_like(p)
            return torch.tensor(1e10, dtype=torch.float64)
        v, grads, _ = got
        for p, g in zip(params, grads):
            p.grad = g
        if v < best["v"]:
            best["v"], best["state"] = v, [p.detach().clone() for p in params]
        return torch.tensor(v, dtype=torch.float64)

    opt.step(closure)
    for p, s in zip(params, best["state"]):
        p.copy_(s)
    got = neg_log_likelihood(Xh, Yh, *params[:4], log_a, gradient=False, noise_floor=noise_floor)
    if got is None:
        raise RuntimeError("fit_gp: the kernel matrix is not positive definite even at the start; are there "
                           "duplicated training rows with different targets?")
    v, _, alpha = got
    if len(Xh) < len(X):  # the posterior over every row, at the hyper-parameters of one row per case
        full = neg_log_likelihood(X, Y, *params[:4], log_a, gradient=False, noise_floor=noise_floor)
        if full is None:
            raise RuntimeError("fit_gp: the kernel matrix over all views is not positive definite at the "
                               "hyper-parameters fitted on one view per case; are two views of different cases "
                               "identical with different targets?")
        alpha = full[2]
    return [p.detach() for p in params[:4]], log_a, v, alpha, evaluations[0]


class GPEnsemble(nn.Module):
    """The mean of several GPs, each on its own columns of the regressor inputs (``model.gp.code_members``).

    Member ``k`` sees ``columns_k`` (the leading ``k`` PCA code components and every state-vector
    column, :func:`liverforce.learn.model.fit_force_model`) and has its own hyper-parameters, fitted
    by its own marginal likelihood (:func:`fit_gp`). The prediction is the members' plain mean. PCA
    codes are nested, so the members are the same model at several code sizes: their mean averages
    over how much of the dent's shape the GP is told, instead of betting on one size (on scenario
    IV's training livers it beat every single size; see ``config/model/default.yaml``).
    """

    def __init__(self, members: list[GPRegressor], columns: list):
        super().__init__()
        if not members or len(members) != len(columns):
            raise ValueError("GPEnsemble: need one column set per member, and at least one member")
        self.members = nn.ModuleList(members)
        for i, cols in enumerate(columns):
            cols = torch.as_tensor(np.asarray(cols), dtype=torch.int64)
            if cols.ndim != 1 or cols.numel() != members[i].X.shape[1]:
                raise ValueError(f"GPEnsemble: member {i} has {members[i].X.shape[1]} inputs but "
                                 f"{cols.numel()} columns")
            self.register_buffer(f"columns_{i}", cols)

    def columns(self, i: int) -> torch.Tensor:
        return getattr(self, f"columns_{i}")

    @staticmethod
    def is_state_dict(state: dict) -> bool:
        return any(str(k).startswith("members.") for k in state)

    @classmethod
    def from_state_dict(cls, state: dict) -> "GPEnsemble":
        n = 1 + max(int(str(k).split(".")[1]) for k in state if str(k).startswith("members."))
        members = [GPRegressor.from_state_dict({k.split(".", 2)[2]: v for k, v in state.items()
                                                if k.startswith(f"members.{i}.")}) for i in range(n)]
        return cls(members, [state[f"columns_{i}"] for i in range(n)])

    @property
    def n_train(self) -> int:
        return self.members[0].n_train

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.forward_members(z).mean(0)

    def forward_members(self, z: torch.Tensor) -> torch.Tensor:
        """Each member's prediction ``(members, n, outputs)``; :meth:`forward` is their mean. How far they
        disagree is what the interval's ``spread`` reads (:mod:`liverforce.learn.interval`)."""
        z = z.double()
        return torch.stack([m(z[:, self.columns(i)]) for i, m in enumerate(self.members)])

    def nearest_distance(self, z, groups=None, row_groups=None) -> np.ndarray:
        """``(n,)``: the members' :meth:`GPRegressor.nearest_distance` of ``z``'s rows on their columns, averaged
        (each member measures in its own length scales; ``groups``, ``row_groups`` as there: the members share
        their training rows)."""
        z = np.asarray(z, dtype=np.float64)
        return np.mean([m.nearest_distance(z[:, self.columns(i).numpy()], groups, row_groups)
                        for i, m in enumerate(self.members)], axis=0)

    def numpy_head(self, fixed: dict | None = None, members: bool = False, distance: bool = False):
        """The members' :meth:`GPRegressor.numpy_head` on their columns, averaged (the compiled paths).

        ``fixed``: ``{input column: value}`` as for :meth:`GPRegressor.numpy_head`; the head then takes the
        other input columns, in their order, and each member gets its share of the fixed inputs. ``members``:
        the head returns ``(mean, sd)``, ``sd`` the members' standard deviation (ddof 1) per output, the mean
        the same bits as without; ValueError for an ensemble of one member (no spread, as
        :meth:`liverforce.learn.model.ForceModel.forward` gives none). ``distance``: the head's result is followed
        by the members' mean of their :meth:`GPRegressor.nearest_distance` (``(mean, distances)``, or
        ``(mean, sd, distances)``), read off each member's kernel matrix."""
        if members and len(self.members) < 2:
            raise ValueError("the members' spread of a GP ensemble of one member is undefined (the sd of one "
                             "prediction); an interval scaled by it needs two or more members")
        cols = [self.columns(i).numpy() for i in range(len(self.members))]
        n_in = 1 + max(int(c.max()) for c in cols)  # the inputs: every column up to the last a member reads
        fixed = _fixed_inputs(fixed, n_in)
        free = {c: k for k, c in enumerate(c for c in range(n_in) if c not in fixed)}  # input -> head column
        heads = [(m.numpy_head({p: fixed[c] for p, c in enumerate(cols[i]) if c in fixed} or None, distance),
                  np.array([free[c] for c in cols[i] if c not in fixed], dtype=np.int64))
                 for i, m in enumerate(self.members)]
        w = 1.0 / len(heads)

        def head(Z: np.ndarray):
            Z = np.asarray(Z, dtype=np.float64)
            if fixed and (Z.ndim != 2 or Z.shape[1] != len(free)):  # (else each member checks its columns)
                raise ValueError(f"the GP head takes rows of {len(free)} inputs, got an array of shape {Z.shape}")
            near = None
            if members:
                each = [h(Z[:, c]) for h, c in heads]
                if distance:
                    near = sum(e[1] for e in each) * w
                    each = [e[0] for e in each]
                out = each[0].copy()
                for e in each[1:]:
                    out += e
            else:
                out = heads[0][0](Z[:, heads[0][1]])
                if distance:
                    out, near = out
                for h, c in heads[1:]:
                    if distance:
                        o, d = h(Z[:, c])
                        out += o
                        near = near + d
                    else:
                        out += h(Z[:, c])
                if distance:
                    near = near * w
            out *= w
            if members:  # the sd about the mean, in a few small in-place operations (np.std on the stacked
                ss = np.zeros_like(out)  # members took ~15 us more per call: a tenth of one cloud's latency)
                for e in each:
                    e -= out
                    e *= e
                    ss += e
                ss *= 1.0 / (len(each) - 1)
                return (out, np.sqrt(ss, out=ss), near) if distance else (out, np.sqrt(ss, out=ss))
            return (out, near) if distance else out

        return head


def fit_gp_ensemble(z: np.ndarray, y: np.ndarray, columns: list, *, seed: int, max_points: int = 2000,
                    iterations: int = 200, groups: np.ndarray | None = None,
                    kernel: str = "rational_quadratic", shape: float | None = 2.0,
                    per_output: bool = False, noise_floor: float = 0.0) -> tuple[GPEnsemble, dict]:
    """One :func:`fit_gp` per column set of ``z``, their mean as a :class:`GPEnsemble`; returns ``(gp, info)``.

    ``info``: the members' :func:`fit_gp` infos under ``members`` and each one's input count under
    ``member_inputs``; ``n_used`` and ``n_likelihood`` as the members' (they share the rows).
    """
    z = np.asarray(z, dtype=np.float64)
    cols = [np.asarray(c, dtype=np.int64) for c in columns]
    for c in cols:
        if c.ndim != 1 or c.size == 0 or c.min() < 0 or c.max() >= z.shape[1]:
            raise ValueError(f"fit_gp_ensemble: a member's columns must index the {z.shape[1]} inputs; got {c}")
    fitted = [fit_gp(z[:, c], y, seed=seed, max_points=max_points, iterations=iterations, groups=groups,
                     kernel=kernel, shape=shape, per_output=per_output, noise_floor=noise_floor) for c in cols]
    infos = [info for _, info in fitted]
    return GPEnsemble([gp for gp, _ in fitted], cols).eval(), {
        "n_used": infos[0]["n_used"], "n_likelihood": infos[0]["n_likelihood"],
        "member_inputs": [int(c.size) for c in cols], "members": infos}
