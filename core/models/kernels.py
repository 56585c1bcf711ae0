"""Kernels of the GP-LVMs (thesis eq. 5.38) and the psi-statistics of the Bayesian GP-LVM (§5.3.4).

RBF:      k(z, z') = s_f^2 exp(-|z - z'|^2 / (2 l^2))
ARD RBF:  k(x, x') = s_f^2 exp(-1/2 sum_q a_q (x_q - x'_q)^2),  a_q = 1 / l_q^2 (inverse squared
          length-scales: a_q -> 0 switches latent dimension q off).

psi-statistics for q(X) = prod_n N(mu_n, diag S_n) (Titsias & Lawrence 2010, eq. 15 and App. B):
  psi0   = sum_n <k(x_n, x_n)>              = N s_f^2
  psi1_nm = <k(x_n, z_m)>                   = s_f^2 prod_q (a_q S_nq + 1)^(-1/2)
                                              exp(-a_q (mu_nq - z_mq)^2 / (2 (a_q S_nq + 1)))
  psi2^n_mm' = <k(z_m, x_n) k(x_n, z_m')>   = s_f^4 prod_q (2 a_q S_nq + 1)^(-1/2)
                                              exp(-a_q (z_mq - z_m'q)^2 / 4
                                                  - a_q (mu_nq - zbar_q)^2 / (2 a_q S_nq + 1)),
  zbar = (z_m + z_m') / 2;   Psi2 = sum_n psi2^n.
"""

from __future__ import annotations

import numpy as np

__all__ = ["sq_dists", "rbf", "ard_rbf", "ard_rbf_grads", "PsiStatistics"]


def sq_dists(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Squared Euclidean distances |a_i - b_j|^2, (n, m), clipped at 0."""
    d2 = np.sum(A**2, 1)[:, None] + np.sum(B**2, 1)[None, :] - 2.0 * A @ B.T
    return np.maximum(d2, 0.0)


def rbf(A: np.ndarray, B: np.ndarray, variance: float, lengthscale: float) -> np.ndarray:
    """Isotropic RBF kernel matrix (eq. 5.38), without the noise term."""
    return variance * np.exp(-0.5 * sq_dists(A, B) / lengthscale**2)


def ard_rbf(A: np.ndarray, B: np.ndarray, variance: float, alpha: np.ndarray) -> np.ndarray:
    """ARD RBF kernel matrix with inverse squared length-scales `alpha` (Q,)."""
    r = np.sqrt(alpha)
    return variance * np.exp(-0.5 * sq_dists(A * r, B * r))


def ard_rbf_grads(G: np.ndarray, Z: np.ndarray, K: np.ndarray, alpha: np.ndarray):
    """Gradients of sum(G * K(Z, Z)) for a symmetric G, K = ard_rbf(Z, Z) (no jitter).

    Returns (dZ (M, Q), d alpha (Q,), d log s_f^2).
    """
    T = G * K
    rows = T.sum(1)
    TZ = T @ Z
    dZ = -2.0 * alpha * (rows[:, None] * Z - TZ)
    dalpha = -(rows @ Z**2 - np.sum(Z * TZ, 0))
    return dZ, dalpha, T.sum()


class PsiStatistics:
    """psi0, psi1, psi2^n for q(X) = prod N(mu_n, diag S_n) under an ARD RBF kernel, with gradients.

    `psi2n` is kept per point (N, M, M); the bound uses Psi2 = psi2n.sum(0). Nothing of size
    N x M x M x Q is formed: psi2 and its gradients go through batched (M x Q) products of
    d = mu_n - Z and the symmetry of dF/dPsi2.
    """

    def __init__(self, mu: np.ndarray, S: np.ndarray, Z: np.ndarray, variance: float, alpha: np.ndarray):
        self.mu, self.S, self.Z, self.variance, self.alpha = mu, S, Z, variance, alpha
        n, q = mu.shape
        self.psi0 = n * variance
        # psi1
        self.den1 = alpha * S + 1.0                                   # (N, Q)
        self.diff1 = mu[:, None, :] - Z[None, :, :]                   # (N, M, Q)
        log_psi1 = (np.log(variance) - 0.5 * np.log(self.den1).sum(1)[:, None]
                    - 0.5 * np.einsum("nmq,nq->nm", self.diff1**2, alpha / self.den1))
        self.psi1 = np.exp(log_psi1)
        # psi2: with d_a = mu_n - z_a, mu_n - zbar_ab = (d_a + d_b) / 2 and z_a - z_b = d_b - d_a, so
        # log psi2^n_ab = 2 log s_f^2 - 1/2 sum_q log den2_nq + u_na + u_nb + sum_q w_nq d_naq d_nbq,
        # u_na = -sum_q (a_q + c_nq) d_naq^2 / 4, w = (a - c) / 2, c = a / den2: one batched
        # (M x Q) (Q x M) product per point instead of N x M x M x Q arrays
        self.den2 = 2.0 * alpha * S + 1.0                             # (N, Q)
        c = alpha / self.den2
        d1 = self.diff1
        u = -0.25 * np.einsum("nmq,nq->nm", d1**2, alpha + c)
        cross = np.matmul(d1 * (0.5 * (alpha - c))[:, None, :], d1.transpose(0, 2, 1))
        const = 2.0 * np.log(variance) - 0.5 * np.log(self.den2).sum(1)
        self.psi2n = np.exp(cross + (u + 0.5 * const[:, None])[:, :, None] + (u + 0.5 * const[:, None])[:, None, :])

    @property
    def psi2(self) -> np.ndarray:
        return self.psi2n.sum(0)

    def gradients(self, g0, g1: np.ndarray, g2: np.ndarray):
        """Chain rule from dF/dpsi0 (scalar, per point psi0_n = s_f^2), dF/dpsi1 (N, M) and a
        symmetric dF/dPsi2 (M, M) to (d mu, d S, d Z, d log s_f^2, d alpha)."""
        a, S, Z = self.alpha, self.S, self.Z
        n = self.mu.shape[0]
        # psi0: sum_n s_f^2
        g0 = np.broadcast_to(np.asarray(g0, dtype=float), (n,))
        dlogvar = float(g0.sum() * self.variance)
        # psi1
        T1 = g1 * self.psi1                                             # (N, M)
        T1_rows = T1.sum(1)[:, None]
        T1_diff = np.einsum("nm,nmq->nq", T1, self.diff1)
        T1_diff2 = np.einsum("nm,nmq->nq", T1, self.diff1**2)
        d_mu = -a / self.den1 * T1_diff
        d_S = -0.5 * a / self.den1 * T1_rows + 0.5 * a**2 / self.den1**2 * T1_diff2
        d_Z = np.einsum("nm,nmq->mq", T1, self.diff1 * (a / self.den1)[:, None, :])
        d_alpha = -0.5 * np.sum(T1_rows * S / self.den1 + T1_diff2 / self.den1**2, 0)
        dlogvar += T1.sum()
        # psi2 (g2 symmetric, shared by all points). With D_abq = mu_nq - zbar_abq =
        # (d_aq + d_bq) / 2 and the symmetry of T2 = g2 * psi2^n, the sums over a, b of T2 D and
        # T2 D^2 and, for d Z, the sums over b of T2 D reduce to T2 d (one batched product)
        T2 = g2[None] * self.psi2n                                      # (N, M, M)
        T2_tot = T2.sum((1, 2))[:, None]
        T2_sum = T2.sum(0)
        T2_rows = T2.sum(2)                                             # (N, M)
        d1 = self.diff1
        Td = np.matmul(T2, d1)                                          # (N, M, Q)
        T2_dbar = np.einsum("nm,nmq->nq", T2_rows, d1)
        T2_dbar2 = 0.5 * (np.einsum("nm,nmq->nq", T2_rows, d1**2) + np.einsum("nmq,nmq->nq", d1, Td))
        dZ2 = 0.5 * np.einsum("nmq,nq->mq", T2_rows[:, :, None] * d1 + Td, 1.0 / self.den2)
        d_mu += -2.0 * a / self.den2 * T2_dbar
        d_S += -a / self.den2 * T2_tot + 2.0 * a**2 / self.den2**2 * T2_dbar2
        sum_rows = T2_sum.sum(1)
        TZ = T2_sum @ Z
        d_alpha += (-np.sum(T2_tot * S / self.den2, 0)
                    - 0.5 * (sum_rows @ Z**2 - np.sum(Z * TZ, 0))
                    - np.sum(T2_dbar2 / self.den2**2, 0))
        d_Z += -a * (sum_rows[:, None] * Z - TZ) + 2.0 * a * dZ2
        dlogvar += 2.0 * T2.sum()
        return d_mu, d_S, d_Z, dlogvar, d_alpha
