"""Benchmark of the shape models: the same data through ours and the peers in one run.

    python bench/models.py [--data vases|psb:<Class>|synthetic] [--shapes 30] [--landmarks 600]
                           [--only ppca|gplvm|bgplvm] [--no-gpy] [--gpy-python PATH] [--seed 0]

Peers: scikit-learn `PCA.score` / `LedoitWolf.score` (PPCA log-likelihood), GPy `GPLVM` and
`BayesianGPLVM`. GPy 1.15 needs numpy 2, so it runs in its own environment (`--gpy-python`,
default /tmp/venvbench/bin/python if present, e.g. a venv with `pip install GPy==1.15.0`): this
script saves the centred Y to .npy, re-runs itself there with `--gpy-worker`, which fits and
saves GPy's optimum to .npz. Fit times are wall-clock of the fit alone in each process
(OPENBLAS_NUM_THREADS=1 in both). Prints fit time, final objective, ratios ours / peer, and
the time to complete 100 partial shapes.

Like-for-like objectives: each model's own number depends on its K_mm jitter (GPy: 1e-8
absolute; ours: 1e-6 s_f^2), so both optima are also evaluated with one implementation (ours:
`gplvm_log_likelihood`, `bgplvm_bound`) at each jitter; the same function at GPy's jitter
reproduces GPy's reported ELBO (printed as a check). "ours reaches GPy's ELBO after" is the
fit time until our running bound first exceeds GPy's final ELBO (and, for the GP-LVM, our
log-likelihood GPy's). Our GP-LVM and BGP-LVM fits try two starting points briefly and
continue the better one; their reported iterations and evaluations count every run (both
starting points, warm-up and the final run).

Targets (reported, not asserted): PPCA = sklearn log-likelihood to 1e-6 relative; GP-LVM >= GPy
log-likelihood and >= 20x faster; BGP-LVM >= GPy ELBO and >= 20x faster; completing 100 partial
shapes <= 1 s (PPCA), <= 10 s (GP-LVMs).

Data (--data):
  vases       (default) `make_vases(--shapes, seed)` -> prepare_meshes -> correspond (our pipeline),
              --landmarks landmarks; the correspondence is cached in bench_output/ so reruns are cheap.
  psb:<Class> every mesh of that PSB class (tests/shared_data.py; 20 shapes), up_axis = 'y', same pipeline.
  synthetic   a template of L points on the unit sphere, stretched along x/y by a (linear), bulged
              along z by sin(2b), sheared by b x^2, plus 1e-3 noise (nearly linear: ARD
              length-scales run off; kept for comparison with earlier runs).
Held-out rows: synthetic draws new shapes; for real data the completion rows are the training
shapes (tiled to 100) with a different hidden region each (landmarks beyond a random plane
through the centre), i.e. completion timing on in-sample shapes.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # shared_data: the real collections
from shared_data import folder_or_exit  # noqa: E402


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


BENCH_OUTPUT = Path(__file__).resolve().parents[1] / "bench_output"
DEFAULT_GPY_PYTHON = "/tmp/venvbench/bin/python"


def real_landmarks(data: str, n_shapes: int, n_landmarks: int, seed: int):
    """Landmark matrix Y (N, 3L) from our pipeline (prepare_meshes + correspond), cached as a
    correspondence .npz in bench_output/."""
    from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes
    from shapegen_core.correspond import Correspondence, CorrespondenceSettings, correspond

    if data == "vases":
        tag = f"vases{n_shapes}_seed{seed}"
    elif data.startswith("psb:"):
        tag = f"psb_{data[4:]}"
    else:
        raise SystemExit(f"unknown --data {data!r} (vases, psb:<Class>, synthetic)")
    path = BENCH_OUTPUT / f"models_corr_{tag}_L{n_landmarks}.npz"
    if path.exists():
        corr = Correspondence.load(path)
        note = f"cached {path.name}"
    else:
        start = time.perf_counter()
        if data == "vases":
            from shapegen_core.demo_data import make_vases
            meshes, up_axis = [s.mesh for s in make_vases(n_shapes, seed=seed)], "z"
        else:
            from shapegen_core.meshes.reading import read_folder
            meshes, up_axis = read_folder(folder_or_exit("psb", data[4:])), "y"
        prepared = prepare_meshes(meshes, PrepareSettings(n_landmarks=n_landmarks, up_axis=up_axis, seed=0))
        corr = correspond(prepared, CorrespondenceSettings(), jobs=1)
        BENCH_OUTPUT.mkdir(exist_ok=True)
        corr.save(path)
        note = f"corresponded in {time.perf_counter() - start:.0f} s, cached as {path.name}"
    return corr.landmark_matrix(), f"{data}: {len(corr)} shapes ({int(corr.outliers.sum())} flagged outliers), {note}"


def plane_masks(Y: np.ndarray, n_rows: int, rng: np.random.Generator):
    """Rows of Y tiled to n_rows, each with the landmarks beyond a random plane through the
    shape's centre hidden (about a third of the coordinates)."""
    rows = Y[np.arange(n_rows) % len(Y)]
    points = rows.reshape(n_rows, -1, 3)
    normals = rng.standard_normal((n_rows, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    proj = np.einsum("nlk,nk->nl", points - points.mean(1, keepdims=True), normals)
    hidden = proj > np.quantile(proj, 2 / 3, axis=1, keepdims=True)
    return rows, np.repeat(~hidden, 3, axis=1)


def gpy_worker(y_path: str, out_path: str, model: str, q: int, m: int, max_iters: int, seed: int) -> None:
    """Fit one GPy model on the saved (centred) Y and save its optimum (runs in GPy's env)."""
    import warnings
    warnings.filterwarnings("ignore")
    import GPy
    Y = np.load(y_path)
    np.random.seed(seed)  # GPy draws initial latent variances / inducing inputs from the global state
    start = time.perf_counter()
    if model == "gplvm":
        peer = GPy.models.GPLVM(Y, q, kernel=GPy.kern.RBF(q))
    else:
        peer = GPy.models.BayesianGPLVM(Y, q, num_inducing=m, kernel=GPy.kern.RBF(q, ARD=True))
    peer.optimize(max_iters=max_iters)
    seconds = time.perf_counter() - start
    run = peer.optimization_runs[-1]
    out = {"seconds": seconds, "objective": float(np.ravel(peer.log_likelihood())[0]),
           "kern_variance": float(np.ravel(peer.kern.variance)[0]),
           "lengthscale": np.atleast_1d(np.asarray(peer.kern.lengthscale, float)),
           "noise_variance": float(np.ravel(peer.likelihood.variance)[0]),
           "n_evals": int(getattr(run, "funct_eval", None) or -1), "status": str(getattr(run, "status", "")),
           "gpy_version": GPy.__version__, "numpy_version": np.__version__}
    if model == "gplvm":
        out["X"] = np.asarray(peer.X, float)
    else:
        out.update(X_mean=np.asarray(peer.X.mean, float), X_variance=np.asarray(peer.X.variance, float),
                   Z=np.asarray(peer.Z, float))
    np.savez(out_path, **out)


def run_gpy(python: str, Yc: np.ndarray, model: str, q: int, m: int, max_iters: int, seed: int):
    """GPy fit in its own interpreter; returns the saved optimum (dict) or an error string."""
    with tempfile.TemporaryDirectory() as folder:
        y_path, out_path = os.path.join(folder, "Y.npy"), os.path.join(folder, "gpy.npz")
        np.save(y_path, Yc)
        env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
        proc = subprocess.run([python, os.path.abspath(__file__), "--gpy-worker", y_path, out_path, model,
                               str(q), str(m), str(max_iters), str(seed)], capture_output=True, text=True, env=env)
        if proc.returncode != 0 or not os.path.exists(out_path):
            return (proc.stderr.strip().splitlines() or ["no output"])[-1]
        with np.load(out_path) as f:
            return {k: f[k].item() if f[k].ndim == 0 else f[k] for k in f.files}


class ObjectiveTrace:
    """Records (time, value) of every evaluation of one of our objectives during a fit
    (`name` in `module`: bgplvm_bound, gplvm_log_likelihood; value = first output)."""

    def __init__(self, module, name: str):
        self.module, self.name, self.original = module, name, getattr(module, name)
        self.times, self.values = [], []

    def __enter__(self):
        def traced(*args, **kwargs):
            out = self.original(*args, **kwargs)
            self.times.append(time.perf_counter())
            self.values.append(out[0])
            return out
        setattr(self.module, self.name, traced)
        self.start = time.perf_counter()
        return self

    def __exit__(self, *exc):
        setattr(self.module, self.name, self.original)

    def time_to_reach(self, target: float):
        hit = np.nonzero(np.asarray(self.values) >= target)[0]
        return (self.times[hit[0]] - self.start, int(hit[0]) + 1) if hit.size else (None, None)

    def reach_text(self, target: float, peer_seconds: float) -> str:
        """When our objective first reached `target` (GPy's optimum), against GPy's fit time."""
        seconds, evaluations = self.time_to_reach(target)
        if seconds is None:
            return "never"
        return f"{seconds:.3f} s ({evaluations} evaluations; GPy's fit / that: {peer_seconds / seconds:.0f}x)"


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def line(name, value=""):
    print(f"  {name:<52s} {value}")


def main(argv=None) -> int:
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "--gpy-worker":
        y_path, out_path, model, q, m, max_iters, seed = sys.argv[2:9]
        gpy_worker(y_path, out_path, model, int(q), int(m), int(max_iters), int(seed))
        return 0
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="vases", help="vases (default), psb:<Class> or synthetic")
    parser.add_argument("--shapes", type=int, default=30, help="shapes (vases, synthetic)")
    parser.add_argument("--landmarks", type=int, default=600)
    parser.add_argument("--test-shapes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-gpy", action="store_true", help="skip the GPy peers")
    parser.add_argument("--gpy-python", default=DEFAULT_GPY_PYTHON if os.path.exists(DEFAULT_GPY_PYTHON) else sys.executable,
                        help="interpreter with GPy 1.15 (numpy 2)")
    parser.add_argument("--only", choices=["ppca", "gplvm", "bgplvm"], help="run one model only")
    parser.add_argument("--gpy-max-iters", type=int, default=1000,
                        help="GPy optimiser iterations (GPy's own default is 1000)")
    args = parser.parse_args(argv)

    models = import_models()
    rng = np.random.default_rng(args.seed)
    if args.data == "synthetic":
        Y, _ = synthetic_shapes(args.shapes, args.landmarks, rng)
        Y_test, _ = synthetic_shapes(args.test_shapes, args.landmarks, rng)
        # partial shapes: hide the landmarks with x > 0.3 of the template (a "rear" region)
        x_coord = Y_test.reshape(len(Y_test), -1, 3)[:, :, 0]
        mask = np.repeat(x_coord <= 0.3, 3, axis=1)
        source = "synthetic shapes (module docstring)"
    else:
        Y, source = real_landmarks(args.data, args.shapes, args.landmarks, args.seed)
        Y_test, mask = plane_masks(Y, args.test_shapes, rng)
    n, d = Y.shape
    mean = Y.mean(0)
    Yc = Y - mean
    print(f"data: {source}\n  {n} shapes x {d // 3} landmarks (D = {d}), {len(Y_test)} "
          f"{'held-out' if args.data == 'synthetic' else 'in-sample (tiled training)'} shapes for completion, "
          f"{100 * (~mask).mean():.0f} % coordinates hidden; numpy {np.__version__}, "
          f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}")
    score_rows = Y_test[:20] if args.data == "synthetic" else None

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
            q = min(ppca.latent_dim, n - 2)  # without shrinkage q = N - 1 leaves no noise variance
            a = models.PPCA(n_components=q, shrinkage=0).fit(Y).score(Y_test)
            b = PCA(n_components=q).fit(Y).score(Y_test)
            line(f"full D, N < D, q = {q} (different sigma^2 conventions): ours / PCA", f"{a:.2f} / {b:.2f} (not comparable, see docs/method.md)")
        times['PPCA'] = completion(ppca, "ours")

    use_gpy = not args.no_gpy

    if run("gplvm"):
        # ------------------------------------------------------------------ GP-LVM
        print("\nGP-LVM (RBF, Q = 2)")
        import shapegen_core.models.gplvm as gplvm_module
        from shapegen_core.models.gplvm import gplvm_log_likelihood
        peer = run_gpy(args.gpy_python, Yc, "gplvm", 2, 0, args.gpy_max_iters, args.seed) if use_gpy else None
        with ObjectiveTrace(gplvm_module, "gplvm_log_likelihood") as trace:
            gplvm, t_ours = timed(lambda: models.GPLVM(n_components=2).fit(Y))
        line("ours: fit", f"{t_ours:.2f} s, {gplvm.n_iter_} iterations, log-likelihood {gplvm.log_likelihood_:.2f}")
        if score_rows is not None:
            line("ours: held-out score (max_z log predictive) / shape", f"{gplvm.score(score_rows):.2f} (20 shapes)")
        if isinstance(peer, str):
            line("GPy GPLVM failed / not importable", peer)
        elif peer is not None:
            ll, t_peer = peer["objective"], peer["seconds"]
            line(f"GPy {peer['gpy_version']} GPLVM: fit", f"{t_peer:.2f} s, {peer['n_evals']} evaluations "
                 f"({peer['status']}), log-likelihood {ll:.2f}")
            x = np.concatenate([peer["X"].ravel(), [np.log(peer["kern_variance"]), np.log(peer["lengthscale"][0]),
                                                    -np.log(peer["noise_variance"])]])
            line("  GPy optimum under our log-likelihood (check)", f"{gplvm_log_likelihood(x, Yc @ Yc.T, d, 2)[0]:.2f}")
            line("ratio log-likelihood ours - GPy / |GPy|", f"{(gplvm.log_likelihood_ - ll) / abs(ll):+.2e} (target >= 0)")
            line("speed-up GPy time / ours", f"{t_peer / t_ours:.1f}x (target >= 20x)")
            line("ours first exceeds GPy's final log-likelihood after", trace.reach_text(ll, t_peer))
        times['GP-LVM'] = completion(gplvm, "ours")

    if run("bgplvm"):
        # ------------------------------------------------------------------ Bayesian GP-LVM
        q, m_ind = 3, min(20, n)
        print(f"\nBayesian GP-LVM (ARD RBF, Q = {q}, M = {m_ind})")
        import shapegen_core.models.bgplvm as bgplvm_module
        from shapegen_core.models.bgplvm import BoundLayout, bgplvm_bound, gram_root
        peer = run_gpy(args.gpy_python, Yc, "bgplvm", q, m_ind, args.gpy_max_iters, args.seed) if use_gpy else None
        with ObjectiveTrace(bgplvm_module, "bgplvm_bound") as trace:
            bgplvm, t_ours = timed(lambda: models.BayesianGPLVM(n_components=q, n_inducing=m_ind,
                                                                random_state=args.seed).fit(Y))
        line("ours: fit", f"{t_ours:.2f} s, {bgplvm.n_iter_} iterations, {len(trace.values)} evaluations, "
             f"ELBO {bgplvm.elbo_:.2f}")
        line("ours: inverse squared length-scales", np.array2string(bgplvm.inverse_lengthscales_, precision=3))
        if score_rows is not None:
            line("ours: held-out score (per-point ELBO) / shape", f"{bgplvm.score(score_rows):.2f} (20 shapes)")
        if isinstance(peer, str):
            line("GPy BayesianGPLVM failed / not importable", peer)
        elif peer is not None:
            elbo, t_peer = peer["objective"], peer["seconds"]
            line(f"GPy {peer['gpy_version']} BayesianGPLVM: fit", f"{t_peer:.2f} s, {peer['n_evals']} evaluations "
                 f"({peer['status']}), ELBO {elbo:.2f}")
            line("GPy inverse squared length-scales", np.array2string(1.0 / peer["lengthscale"] ** 2, precision=3))
            layout, root = BoundLayout(n, q, m_ind), gram_root(Yc @ Yc.T)

            def bound(mu, S, Z, var, alpha, noise, absolute_jitter=None):
                """Our bound at these parameters; K_mm jitter absolute (GPy's 1e-8) or ours."""
                x = layout.pack(mu, np.log(S), Z, np.log(var), np.log(alpha), -np.log(noise))
                jitter = bgplvm.jitter_ if absolute_jitter is None else absolute_jitter / var
                try:
                    return bgplvm_bound(x, layout, root, d, jitter)[0]
                except np.linalg.LinAlgError:
                    return float("nan")
            ours_p = (bgplvm.latent_mean_, bgplvm.latent_variance_, bgplvm.inducing_, bgplvm.kernel_variance_,
                      bgplvm.inverse_lengthscales_, bgplvm.noise_variance_)
            gpy_p = (peer["X_mean"], peer["X_variance"], peer["Z"], peer["kern_variance"],
                     1.0 / peer["lengthscale"] ** 2, peer["noise_variance"])
            g_own = bound(*gpy_p, absolute_jitter=1e-8)
            line("  GPy optimum under our bound at GPy's jitter (check)",
                 f"{g_own:.2f} (rel diff to GPy's own {abs(g_own / elbo - 1):.1e})")
            for label, kw in (("jitter 1e-8 absolute (GPy's)", {"absolute_jitter": 1e-8}),
                              (f"jitter {bgplvm.jitter_:g} s_f^2 (ours)", {})):
                a, b = bound(*ours_p, **kw), bound(*gpy_p, **kw)
                line(f"like-for-like, our bound, {label}: ours / GPy",
                     f"{a:.2f} / {b:.2f}, (ours - GPy) / |GPy| {(a - b) / abs(b):+.2e}")
            line("ratio ELBO (own numbers) ours - GPy / |GPy|", f"{(bgplvm.elbo_ - elbo) / abs(elbo):+.2e} (target >= 0)")
            line("speed-up GPy time / ours", f"{t_peer / t_ours:.1f}x (target >= 20x)")
            line("ours first exceeds GPy's final ELBO after", trace.reach_text(elbo, t_peer))
        times['BGP-LVM'] = completion(bgplvm, "ours")

    print("\ncompletion of 100 partial shapes (targets: PPCA <= 1 s, GP-LVMs <= 10 s): "
          + ", ".join(f"{k} {v:.2f} s" for k, v in times.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
