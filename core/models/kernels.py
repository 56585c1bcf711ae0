"""Kernels of the GP-LVMs (thesis eq. 5.38) and the psi-statistics of the Bayesian GP-LVM (§5.3.4).

RBF:      k(z, z') = s_f^2 exp(-|z - z'|^2 / (2 l^2))                       (eq. 5.38; GP-LVM)
ARD RBF:  k(x, x') = s_f^2 exp(-1/2 sum_q a_q (x_q - x'_q)^2),  a_q = 1 / l_q^2 (inverse squared
          length-scales: a_q -> 0 switches latent dimension q off; Bayesian GP-LVM), i.e. the
          RBF kernel with l = 1 on inputs scaled by sqrt(a_q): one `rbf` serves both.

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

from functools import lru_cache

import numpy as np

__all__ = ["sq_dists", "rbf", "rbf_from_sq_dists", "PsiStatistics"]


def sq_dists(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Squared Euclidean distances |a_i - b_j|^2, (n, m), clipped at 0."""
    d2 = np.sum(A**2, 1)[:, None] + np.sum(B**2, 1)[None, :] - 2.0 * A @ B.T
    return np.maximum(d2, 0.0)


def rbf_from_sq_dists(d2: np.ndarray, variance: float, squared_lengthscale: float = 1.0) -> np.ndarray:
    """The RBF kernel (eq. 5.38) of squared distances d2 = |z - z'|^2."""
    return variance * np.exp(-0.5 * d2 / squared_lengthscale)


def rbf(A: np.ndarray, B: np.ndarray, variance: float, squared_lengthscale: float = 1.0) -> np.ndarray:
    """RBF kernel matrix k(A, B), without the noise term; the ARD kernel is
    rbf(A * sqrt(a), B * sqrt(a), variance)."""
    return rbf_from_sq_dists(sq_dists(A, B), variance, squared_lengthscale)


@lru_cache(maxsize=8)
def _pair_operators(m: int) -> tuple[np.ndarray, np.ndarray]:
    """(M^2, M) matrices mapping Z to (z_a + z_b) / 2 and to z_a - z_b for all pairs (a, b)."""
    first = np.repeat(np.eye(m), m, axis=0)                     # row (a, b) -> e_a
    second = np.tile(np.eye(m), (m, 1))                         # row (a, b) -> e_b
    mean_pairs, diff_pairs = 0.5 * (first + second), first - second
    mean_pairs.flags.writeable = diff_pairs.flags.writeable = False
    return mean_pairs, diff_pairs


class PsiStatistics:
    """psi0, psi1, psi2^n for q(X) = prod N(mu_n, diag S_n) under the ARD RBF kernel, and
    K_mm = K(Z, Z) + jitter s_f^2 I, with gradients.

    Each log-statistic is linear in a few features of Z, with per-point coefficients
    (w = a / (a S + 1), c = a / (2 a S + 1), N x Q; zbar_ab = (z_a + z_b) / 2):

      log psi1_nm   = [w mu, -w / 2, k1] . [z_m, z_m^2, 1],
      log psi2^n_ab = [2 c mu, -c, k2, -1/4] . [zbar_ab, zbar_ab^2, 1, u_ab],
      log K_ab      = log s_f^2 - 1/2 u_ab,      u_ab = sum_q a_q (z_aq - z_bq)^2,
      k1 = log s_f^2 - 1/2 sum_q (log(a S + 1) + w mu^2),  k2 = 2 log s_f^2 - sum_q (1/2 log(2 a S + 1) + c mu^2),

    so every statistic is one (N x K) (K x M or M^2) product and an exp, and every gradient a
    product of T = dF/dpsi * psi with the same features (nothing N x M x Q or N x M x M x Q).
    `psi2n` is kept per point (N, M, M); the bound uses Psi2 = psi2n.sum(0).
    """

    def __init__(self, mu: np.ndarray, S: np.ndarray, Z: np.ndarray, variance: float, alpha: np.ndarray,
                 jitter: float = 0.0):
        self.mu, self.S, self.Z, self.variance, self.alpha, self.jitter = mu, S, Z, variance, alpha, jitter
        n, q = mu.shape
        m = Z.shape[0]
        self.psi0 = n * variance
        log_var = np.log(variance)
        mean_pairs, diff_pairs = _pair_operators(m)
        self.delta_sq = np.square(diff_pairs @ Z)                                    # (z_a - z_b)^2, (M^2, Q)
        u = self.delta_sq @ alpha                                                   # (M^2,)
        self.features1 = np.concatenate([Z, Z * Z, np.ones((m, 1))], 1)                # (M, 2Q + 1)
        # [zbar, zbar^2, 1, u] (M^2, 2Q + 2): the u column carries the -u/4 of log psi2
        self.features2 = np.empty((m * m, 2 * q + 2))
        z_bar = np.matmul(mean_pairs, Z, out=self.features2[:, :q])
        np.square(z_bar, out=self.features2[:, q: 2 * q])
        self.features2[:, 2 * q] = 1.0
        self.features2[:, 2 * q + 1] = u
        self.inv_den1 = 1.0 / (alpha * S + 1.0)
        self.inv_den2 = 1.0 / (2.0 * alpha * S + 1.0)
        self.w = alpha * self.inv_den1
        self.c = alpha * self.inv_den2
        w_mu, c_mu = self.w * mu, self.c * mu
        k1 = log_var + (0.5 * np.log(self.inv_den1) - 0.5 * w_mu * mu).sum(1)
        k2 = 2.0 * log_var + (0.5 * np.log(self.inv_den2) - c_mu * mu).sum(1)
        self.coef1 = np.concatenate([w_mu, -0.5 * self.w, k1[:, None]], 1)
        self.coef2 = np.concatenate([2.0 * c_mu, -self.c, k2[:, None], np.full((n, 1), -0.25)], 1)
        self.psi1 = np.exp(self.coef1 @ self.features1.T)
        self.psi2n = np.exp(self.coef2 @ self.features2.T).reshape(n, m, m)
        self.Kmm = rbf_from_sq_dists(u, variance).reshape(m, m)
        self.Kmm.flat[:: m + 1] += jitter * variance

    @property
    def psi2(self) -> np.ndarray:
        return self.psi2n.sum(0)

    def gradients(self, g0: float, g1: np.ndarray, g2: np.ndarray, g_kmm: np.ndarray | None = None):
        """Chain rule from dF/dpsi0 (scalar; psi0 = N s_f^2), dF/dpsi1 (N, M), a symmetric
        dF/dPsi2 (M, M) and optionally a symmetric dF/dK_mm (M, M) to
        (d mu, d S, d Z, d log s_f^2, d alpha).

        With T1 = g1 * psi1, T2 = g2 * psi2^n, T_K = g_kmm * K_mm: dF/dcoef = T @ features and
        dF/dfeatures = T^T coef (class docstring), then the coefficients' and features'
        derivatives; u enters through U = sum_n T2 / 4 + T_K / 2 (d u_ab / d z = 2 a (z_a - z_b)).
        """
        mu, S, Z, a = self.mu, self.S, self.Z, self.alpha
        n, q = mu.shape
        m = Z.shape[0]
        w, c = self.w, self.c
        T1 = g1 * self.psi1                                                          # (N, M)
        T2 = g2.ravel() * self.psi2n.reshape(n, m * m)                               # (N, M^2)
        S1 = T1 @ self.features1                                                     # sums of T1 z, T1 z^2, T1
        S2 = T2 @ self.features2                                                     # sums of T2 zbar, zbar^2, T2
        T1_z, T1_z2, r1 = S1[:, :q], S1[:, q:2 * q], S1[:, 2 * q:]
        T2_z, T2_z2, t2 = S2[:, :q], S2[:, q:2 * q], S2[:, 2 * q: 2 * q + 1]
        d_w = mu * T1_z - 0.5 * T1_z2 - 0.5 * r1 * mu**2                             # dF/dw = -Q1 / 2
        d_c = 2.0 * mu * T2_z - T2_z2 - t2 * mu**2                                   # dF/dc = -Q2
        d_mu = w * (T1_z - r1 * mu) + 2.0 * c * (T2_z - t2 * mu)
        # dw/dS = -w^2, dc/dS = -2 c^2, dw/da = 1 / den1^2, dc/da = 1 / den2^2
        d_S = -w**2 * d_w - 0.5 * w * r1 - 2.0 * c**2 * d_c - c * t2
        d_alpha = (d_w * self.inv_den1**2 - 0.5 * r1 * S * self.inv_den1
                   + d_c * self.inv_den2**2 - t2 * S * self.inv_den2).sum(0)
        U = 0.25 * T2.sum(0).reshape(m, m)
        d_logvar = g0 * n * self.variance + r1.sum() + 2.0 * t2.sum()
        if g_kmm is not None:
            T_K = g_kmm * self.Kmm
            U += 0.5 * T_K
            d_logvar += T_K.sum()
        d_alpha -= U.ravel() @ self.delta_sq
        # Z: through z (psi1), zbar and zbar^2 (psi2; T2 symmetric in a, b) and u:
        # E1 = T1^T coef1, E2 = r2^T coef2 with r2_na = sum_b T2_nab, T2_Z[n] = T2_n Z
        E1 = T1.T @ self.coef1
        T2_F = (T2.reshape(n * m, m) @ self.features1).reshape(n, m, 2 * q + 1)       # T2_n [Z, Z^2, 1]
        E2 = T2_F[:, :, 2 * q].T @ self.coef2[:, : 2 * q]
        U_F = U @ self.features1
        d_Z = (E1[:, :q] + E2[:, :q] + np.einsum("naq,nq->aq", T2_F[:, :, :q], self.coef2[:, q: 2 * q])
               + 4.0 * a * U_F[:, :q] + Z * (2.0 * E1[:, q: 2 * q] + E2[:, q:] - 4.0 * a * U_F[:, 2 * q:]))
        return d_mu, d_S, d_Z, float(d_logvar), d_alpha
