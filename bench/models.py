"""Benchmark of the shape models (issue 4): the same data through ours and the peers in one run.

    python bench/models.py [--shapes 30] [--landmarks 600] [--no-gpy] [--seed 0]

Peers: scikit-learn `PCA.score` / `LedoitWolf.score` (PPCA log-likelihood), GPy `GPLVM` and
`BayesianGPLVM` (if importable; GPy 1.15 needs numpy 2, e.g. a separate venv with
`pip install GPy==1.15.0 scikit-learn` and this repository on the path). Prints fit time, final
objective and ratios ours / peer, plus the time to complete 100 partial shapes.

Targets (reported, not asserted): PPCA = sklearn log-likelihood to 1e-6 relative; GP-LVM >= GPy
log-likelihood and >= 20x faster; BGP-LVM >= GPy ELBO and >= 20x faster; completing 100 partial
shapes <= 1 s (PPCA), <= 10 s (GP-LVMs).

Data: synthetic shapes with a known low-dimensional, non-linear parametrisation: a template of
L points on the unit sphere, stretched along x/y by a (linear), bulged along z by sin(2b) and
sheared by b x^2 (non-linear), plus 1e-3 Gaussian noise. Centred Y is given to every model.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402


def import_models():
    """shapegen_core.models, installed or straight from this repository's core/ directory."""
    try:
        import shapegen_core.models as models
        return models
    except ImportError:
        core = Path(__file__).resolve().parents[1] / "core"
        spec = importlib.util.spec_from_file_location("shapegen_core", core / "__init__.py",
                                                      submodule_search_locations=[str(core)])
        package = importlib.util.module_from_spec(spec)
        sys.modules["shapegen_core"] = package
        spec.loader.exec_module(package)
        import shapegen_core.models as models
        return models


def synthetic_shapes(n: int, n_landmarks: int, rng: np.random.Generator, noise: float = 1e-3):
    """(Y (n, 3L), latent parameters (n, 2)) from the parametrisation in the module docstring."""
    template = np.random.default_rng(12345).standard_normal((n_landmarks, 3))
    template /= np.linalg.norm(template, axis=1, keepdims=True)
    params = rng.uniform(-1, 1, (n, 2))
    shapes = []
    for a, b in params:
        p = template * np.array([1 + 0.4 * a, 1 - 0.2 * a, 1 + 0.3 * np.sin(2 * b)])
        p[:, 2] += 0.3 * b * p[:, 0] ** 2
        shapes.append(p.ravel())
    Y = np.array(shapes)
    return Y + noise * rng.standard_normal(Y.shape), params


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def line(name, value=""):
    print(f"  {name:<52s} {value}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", type=int, default=30)
    parser.add_argument("--landmarks", type=int, default=600)
    parser.add_argument("--test-shapes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-gpy", action="store_true", help="skip the GPy peers")
    parser.add_argument("--only", choices=["ppca", "gplvm", "bgplvm"], help="run one model only")
    parser.add_argument("--gpy-max-iters", type=int, default=1000,
                        help="GPy optimiser iterations (GPy's own default is 1000)")
    args = parser.parse_args(argv)

    models = import_models()
    rng = np.random.default_rng(args.seed)
    Y, _ = synthetic_shapes(args.shapes, args.landmarks, rng)
    Y_test, _ = synthetic_shapes(args.test_shapes, args.landmarks, rng)
    n, d = Y.shape
    mean = Y.mean(0)
    Yc = Y - mean
    # partial shapes: hide the landmarks with x > 0.3 of the template (a "rear" region)
    x_coord = Y_test.reshape(len(Y_test), -1, 3)[:, :, 0]
    mask = np.repeat(x_coord <= 0.3, 3, axis=1)
    print(f"data: {n} shapes x {args.landmarks} landmarks (D = {d}), {len(Y_test)} test shapes, "
          f"{100 * (~mask).mean():.0f} % coordinates hidden for completion; numpy {np.__version__}")

    def completion(model, label):
        filled, seconds = timed(lambda: model.complete(np.where(mask, Y_test, np.nan), mask))
        err = np.mean(np.sum(((filled - Y_test) * ~mask) ** 2, 1))
        line(f"{label}: complete {len(Y_test)} partial shapes", f"{seconds:.2f} s, mean summed sq. error "
             f"{err:.3g} (mean-shape fill: {np.mean(np.sum(((mean - Y_test) * ~mask) ** 2, 1)):.3g})")
        return seconds

    run = lambda name: args.only in (None, name)  # noqa: E731
    times = {}
    if run("ppca"):
        # ------------------------------------------------------------------ PPCA
        print("\nPPCA")
        ppca, t_fit = timed(lambda: models.PPCA().fit(Y))
        line("ours (Ledoit-Wolf, 80 % rule): fit", f"{t_fit * 1e3:.1f} ms, q = {ppca.latent_dim}, "
             f"shrinkage {ppca.shrinkage_:.4g}")
        line("ours: held-out log-likelihood / shape", f"{ppca.score(Y_test):.6f}")
        try:
            from sklearn.covariance import LedoitWolf, ledoit_wolf_shrinkage
            from sklearn.decomposition import PCA
        except ImportError:
            line("scikit-learn not importable: PPCA peer comparison skipped")
        else:
            s_ours, s_sk = ppca.shrinkage_, ledoit_wolf_shrinkage(Y)
            line("Ledoit-Wolf shrinkage ours / sklearn", f"{s_ours:.12g} / {s_sk:.12g} (rel diff {abs(s_ours / s_sk - 1):.1e})")
            full = models.PPCA(n_components=n - 1).fit(Y)
            (lw, t_lw) = timed(lambda: LedoitWolf().fit(Y))
            a, b = full.score(Y_test), lw.score(Y_test)
            line("q = N-1 (= Ledoit-Wolf covariance): ours / sklearn LW", f"{a:.8f} / {b:.8f}  rel diff {abs(a / b - 1):.1e}")
            line("  fit time ours / sklearn LedoitWolf (D x D)", f"{1e3 * timed(lambda: models.PPCA(n_components=n - 1).fit(Y))[1]:.1f} ms / {1e3 * t_lw:.1f} ms")
            # PCA.score: like with like needs N > D (sklearn averages the discarded eigenvalues over
            # min(N, D) - q dims, ML over D - q) and its ddof = 1 covariance (data rescaled)
            d_small = min(d, n - 6)
            Ys, Yts = Y[:, :d_small], Y_test[:, :d_small]
            scaled = Ys.mean(0) + (Ys - Ys.mean(0)) * np.sqrt((n - 1) / n)
            q = min(ppca.latent_dim, d_small - 1)
            a = models.PPCA(n_components=q, shrinkage=0).fit(Ys).score(Yts)
            b = PCA(n_components=q).fit(scaled).score(Yts)
            line(f"shrinkage off, first {d_small} coords, q = {q}: ours / PCA.score", f"{a:.8f} / {b:.8f}  rel diff {abs(a / b - 1):.1e}")
            a = models.PPCA(n_components=ppca.latent_dim, shrinkage=0).fit(Y).score(Y_test)
            b = PCA(n_components=ppca.latent_dim).fit(Y).score(Y_test)
            line("full D, N < D (different sigma^2 conventions): ours / PCA", f"{a:.2f} / {b:.2f} (not comparable, see method.md)")
        times['PPCA'] = completion(ppca, "ours")

    # ------------------------------------------------------------------ GPy
    GPy = None
    if not args.no_gpy:
        try:
            import GPy  # noqa: F811
        except Exception as exc:  # ImportError, or a binary incompatibility
            print(f"\nGPy not importable ({type(exc).__name__}: {exc}); GPy comparisons skipped. "
                  "GPy 1.15 needs numpy 2: create a venv with `pip install GPy==1.15.0 scikit-learn`.")

    if run("gplvm"):
        # ------------------------------------------------------------------ GP-LVM
        print("\nGP-LVM (RBF, Q = 2)")
        gplvm, t_ours = timed(lambda: models.GPLVM(n_components=2).fit(Y))
        line("ours: fit", f"{t_ours:.2f} s, {gplvm.n_iter_} iterations, log-likelihood {gplvm.log_likelihood_:.2f}")
        line("ours: held-out score (max_z log predictive) / shape", f"{gplvm.score(Y_test[:20]):.2f} (20 shapes)")
        if GPy is not None:
            def fit_gpy_gplvm():
                m = GPy.models.GPLVM(Yc, 2, kernel=GPy.kern.RBF(2))
                m.optimize(max_iters=args.gpy_max_iters)
                return m
            peer, t_peer = timed(fit_gpy_gplvm)
            ll = float(np.ravel(peer.log_likelihood())[0])
            line("GPy GPLVM: fit", f"{t_peer:.2f} s, log-likelihood {ll:.2f}")
            line("ratio log-likelihood ours - GPy / |GPy|", f"{(gplvm.log_likelihood_ - ll) / abs(ll):+.2e} (target >= 0)")
            line("speed-up GPy time / ours", f"{t_peer / t_ours:.1f}x (target >= 20x)")
        times['GP-LVM'] = completion(gplvm, "ours")

    if run("bgplvm"):
        # ------------------------------------------------------------------ Bayesian GP-LVM
        print("\nBayesian GP-LVM (ARD RBF, Q = 3, M = 20)")
        bgplvm, t_ours = timed(lambda: models.BayesianGPLVM(n_components=3, n_inducing=20, random_state=args.seed).fit(Y))
        line("ours: fit", f"{t_ours:.2f} s, {bgplvm.n_iter_} iterations, ELBO {bgplvm.elbo_:.2f}")
        line("ours: inverse squared length-scales", np.array2string(bgplvm.inverse_lengthscales_, precision=3))
        line("ours: held-out score (per-point ELBO) / shape", f"{bgplvm.score(Y_test[:20]):.2f} (20 shapes)")
        if GPy is not None:
            def fit_gpy_bgplvm():
                m = GPy.models.BayesianGPLVM(Yc, 3, num_inducing=20, kernel=GPy.kern.RBF(3, ARD=True))
                m.optimize(max_iters=args.gpy_max_iters)
                return m
            np.random.seed(args.seed)  # GPy draws its initial inducing inputs from the global state
            peer, t_peer = timed(fit_gpy_bgplvm)
            elbo = float(np.ravel(peer.log_likelihood())[0])
            line("GPy BayesianGPLVM: fit", f"{t_peer:.2f} s, ELBO {elbo:.2f} (its K_mm jitter: 1e-8 absolute)")
            # the bound depends on the K_mm jitter (ours: 1e-6 s_f^2): evaluate both optima with
            # our bound function at GPy's absolute jitter 1e-8 (the values may be rounding-limited
            # when the length-scales are long)
            from shapegen_core.models.bgplvm import BoundLayout, bgplvm_bound, gram_root
            layout, root = BoundLayout(n, 3, 20), gram_root(Yc @ Yc.T)

            def bound_at_gpy_jitter(mu, S, Z, var, alpha, noise):
                x = layout.pack(mu, np.log(S), Z, np.log(var), np.log(alpha), -np.log(noise))
                try:
                    return bgplvm_bound(x, layout, root, d, 1e-8 / var)[0]
                except np.linalg.LinAlgError:
                    return float("nan")
            g_var = float(np.ravel(peer.kern.variance)[0])
            ours_common = bound_at_gpy_jitter(bgplvm.latent_mean_, bgplvm.latent_variance_, bgplvm.inducing_,
                                              bgplvm.kernel_variance_, bgplvm.inverse_lengthscales_, bgplvm.noise_variance_)
            gpy_common = bound_at_gpy_jitter(np.asarray(peer.X.mean), np.asarray(peer.X.variance), np.asarray(peer.Z),
                                             g_var, 1.0 / np.asarray(peer.kern.lengthscale) ** 2,
                                             float(np.ravel(peer.likelihood.variance)[0]))
            line("same bound, jitter 1e-8 absolute: ours / GPy optimum", f"{ours_common:.2f} / {gpy_common:.2f}")
            line("ratio ELBO ours - GPy / |GPy|", f"{(bgplvm.elbo_ - elbo) / abs(elbo):+.2e} (target >= 0)")
            line("speed-up GPy time / ours", f"{t_peer / t_ours:.1f}x (target >= 20x)")
        times['BGP-LVM'] = completion(bgplvm, "ours")

    print("\ncompletion of 100 partial shapes (targets: PPCA <= 1 s, GP-LVMs <= 10 s): "
          + ", ".join(f"{k} {v:.2f} s" for k, v in times.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
