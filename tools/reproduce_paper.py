#!/usr/bin/env python
"""Reproduce the MKC-EM paper's Example 1 (Fig. 4, Fig. 5), Example 2 (Table I) and Fig. 3.

    python tools/reproduce_paper.py                 # everything, 200 Monte Carlo runs (a few minutes)
    python tools/reproduce_paper.py --runs 40       # quicker
    python tools/reproduce_paper.py --only table1 --json out/table1.json

Unstated in the paper, chosen here: x_k ~ U(-5, 5) in Example 2 (gives WLS errors within a few
percent of Table I); theta_o = 1 and N = 100 in Example 1; truncation a = 20 in Fig. 3 (the
uniform's support). Seeds are fixed and disjoint from those used while developing the defaults.
Figures are saved as PNG when matplotlib is installed.
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import time
import warnings

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from mkc_stream import MKCRegressor, WLSRegressor  # noqa: E402
from mkc_stream.kernels.estep import estep_channel  # noqa: E402
from mkc_stream.pdf import mkc_logpdf  # noqa: E402

SEED = 20261121

#: Table I of the paper: (p1, p2) and mean error of WLS, LAD, MKC (sigma = 0.5), MKC-EM.
#: Case 6 as written (40% / 20% outliers from U(0, 10) / U(0, 20)) shifts the mean noise by 2 in both
#: channels, so WLS errs by ~2 (2.02 over 200 runs here, the paper 0.47) and LAD by 0.41 (paper 0.13):
#: the paper's case-6 data were milder than its text, and its MKC-EM 0.063 is no like-for-like target.
#: Here MKC-EM's case-6 excess over the true-noise ML (0.094 vs 0.052) is the symmetric kernel's
#: bias under one-sided outliers, the same from any start (tests/test_paper.py).
PAPER_TABLE_I = {
    1: ((1.0, 1.0), {"WLS": 0.0395, "LAD": 0.0567, "MKC": 0.0508, "MKC-EM": 0.0395}),
    2: ((0.8, 1.0), {"WLS": 0.1745, "LAD": 0.0585, "MKC": 0.0545, "MKC-EM": 0.0450}),
    3: ((1.0, 0.8), {"WLS": 0.1002, "LAD": 0.0567, "MKC": 0.0499, "MKC-EM": 0.0380}),
    4: ((0.8, 0.8), {"WLS": 0.1998, "LAD": 0.0606, "MKC": 0.0495, "MKC-EM": 0.0418}),
    5: ((0.8, 0.6), {"WLS": 0.3653, "LAD": 0.0711, "MKC": 0.0558, "MKC-EM": 0.0504}),
    6: ((0.6, 0.8), {"WLS": 0.4726, "LAD": 0.1314, "MKC": 0.0747, "MKC-EM": 0.0628}),
}


# ----------------------------------------------------------------------------- data
def example2_noise(rng, N, case, p1, p2):
    """Eq. (35) for cases 1-4; Gaussian outliers (variance 100 / 200) in case 5; U(0, 10)/U(0, 20) in case 6."""
    g1 = rng.random(N) < p1
    g2 = rng.random(N) < p2
    n1, n2 = rng.normal(0, 0.5, N), rng.normal(0, 1.0, N)
    if case == 5:
        o1, o2 = rng.normal(0, 10.0, N), rng.normal(0, math.sqrt(200.0), N)
    elif case == 6:
        o1, o2 = rng.uniform(0, 10, N), rng.uniform(0, 20, N)
    else:
        o1, o2 = rng.uniform(-10, 10, N), rng.uniform(-20, 20, N)
    return np.stack([np.where(g1, n1, o1), np.where(g2, n2, o2)], 1)


def example2(rng, case, N=100):
    (p1, p2), _ = PAPER_TABLE_I[case]
    x = rng.uniform(-5, 5, N)
    Xk = np.stack([np.ones(N), x], 1)
    X = np.stack([Xk, Xk], 1)
    theta = np.ones(2)
    return X, X @ theta + example2_noise(rng, N, case, p1, p2), theta


def example1(rng, N=100, theta=1.0):
    k = np.arange(1, N + 1)
    x = 8 * np.sin(0.04 * np.pi * k)
    v = np.where(rng.random(N) < 0.9, rng.normal(0, 0.5, N), rng.uniform(-20, 20, N))   # eq. (33)
    return x[:, None], x * theta + v, np.array([theta])


# ----------------------------------------------------------------------------- estimators
def oracle_mle(X, Y, case):
    """Maximum likelihood under the TRUE noise mixture (knows p, the outlier law): a yardstick."""
    from scipy.optimize import minimize

    (p1, p2), _ = PAPER_TABLE_I[case]

    def comp(r, p, sd, lo, hi, gsd):
        head = p * np.exp(-r * r / (2 * sd * sd)) / (sd * math.sqrt(2 * math.pi))
        if gsd:
            tail = (1 - p) * np.exp(-r * r / (2 * gsd * gsd)) / (gsd * math.sqrt(2 * math.pi))
        else:
            tail = (1 - p) * ((r >= lo) & (r <= hi)) / (hi - lo)
        return head + tail

    def nll(t):
        r = Y - np.einsum("kmn,n->km", X, t)
        if case == 5:
            l1, l2 = comp(r[:, 0], p1, 0.5, 0, 0, 10.0), comp(r[:, 1], p2, 1.0, 0, 0, math.sqrt(200))
        elif case == 6:
            l1, l2 = comp(r[:, 0], p1, 0.5, 0, 10, 0), comp(r[:, 1], p2, 1.0, 0, 20, 0)
        else:
            l1, l2 = comp(r[:, 0], p1, 0.5, -10, 10, 0), comp(r[:, 1], p2, 1.0, -20, 20, 0)
        return -np.sum(np.log(l1 + 1e-300)) - np.sum(np.log(l2 + 1e-300))

    starts = [MKCRegressor(sigma=20, d=[1, 2]).fit(X, Y).coef_]
    best = min((minimize(nll, s, method="Nelder-Mead", options={"xatol": 1e-9, "fatol": 1e-11}) for s in starts),
               key=lambda r: r.fun)
    return best.x


def estimator_table(include_peers=True):
    """name -> callable(X, Y) -> theta. Channel weights d = [1, 2] as in the paper where applicable."""
    est = {
        "WLS": lambda X, Y: WLSRegressor(d=[1, 2]).fit(X, Y).coef_,
        "MKC": lambda X, Y: MKCRegressor(em=False, sigma=0.5, d=[1, 2]).fit(X, Y).coef_,
        "MKC-EM": lambda X, Y: MKCRegressor(em=True, sigma=20, d=[1, 2], max_em_iter=10).fit(X, Y).coef_,
        "MKC-EM(3)": lambda X, Y: MKCRegressor(em=True, sigma=20, d=[1, 2], max_em_iter=3).fit(X, Y).coef_,
    }
    try:
        from mkc_stream.baselines import BASELINES
    except ImportError:
        BASELINES = {}
    if "lad" in BASELINES:
        est["LAD"] = lambda X, Y: BASELINES["lad"](channel_scale=[1, 2]).fit(X, Y).coef_
    if not include_peers:
        return est
    for key, name in [("huber", "Huber"), ("lts", "LTS"), ("lms", "LMS"), ("ransac", "RANSAC"), ("lel", "LEL"),
                      ("r3-huber", "R3-Huber"), ("r3-huber-eps", "R3-HuberEps"), ("ridge", "Ridge"), ("lasso", "Lasso")]:
        if key in BASELINES:
            est[name] = (lambda cls: (lambda X, Y: cls(channel_scale=[1, 2]).fit(X, Y).coef_))(BASELINES[key])
    try:
        import statsmodels.api as sm

        def tukey(X, Y):
            Xs = np.concatenate([X[:, 0, :], X[:, 1, :] / 2])
            Ys = np.concatenate([Y[:, 0], Y[:, 1] / 2])
            return sm.RLM(Ys, Xs, M=sm.robust.norms.TukeyBiweight()).fit().params

        est["RLM-Tukey"] = tukey
    except ImportError:
        pass
    return est


# ----------------------------------------------------------------------------- studies
def table1(runs, include_peers=True, oracle=True, progress=True):
    est = estimator_table(include_peers)
    if oracle:
        est["oracle-MLE"] = None
    results = {}
    for case in PAPER_TABLE_I:
        rng = np.random.default_rng(SEED + case)
        errs = {k: [] for k in est}
        times = {k: [] for k in est}
        for r in range(runs):
            X, Y, th = example2(rng, case)
            for name, f in est.items():
                t0 = time.perf_counter()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    theta = oracle_mle(X, Y, case) if name == "oracle-MLE" else f(X, Y)
                times[name].append(time.perf_counter() - t0)
                errs[name].append(float(np.linalg.norm(theta - th)))
            if progress and (r + 1) % max(1, runs // 10) == 0:
                print(f"\r  case {case}: {r + 1}/{runs} runs", end="", file=sys.stderr, flush=True)
        if progress:
            print("", file=sys.stderr)
        results[case] = {k: {"mean": float(np.mean(v)), "std": float(np.std(v)), "errors": v,
                             "time_median_s": float(np.median(times[k]))} for k, v in errs.items()}
    return results


def print_table1(results, runs):
    print(f"\nTable I - Example 2, ||theta - theta_o||_2, mean +- std over {runs} runs (paper in brackets)")
    names = list(next(iter(results.values())).keys())
    for case, res in results.items():
        (p1, p2), paper = PAPER_TABLE_I[case]
        print(f"\n case {case}  [p1, p2] = [{p1}, {p2}]")
        for name in names:
            r = res[name]
            pp = f"[{paper[name]:.4f}]" if name in paper else ""
            dev = f"{(r['mean'] / paper[name] - 1) * 100:+6.1f}%" if name in paper else ""
            print(f"   {name:12s} {r['mean']:.4f} +- {r['std']:.4f}  {pp:9s} {dev:8s}  {r['time_median_s'] * 1e3:8.3f} ms")
        if "MKC-EM" in res:
            em = np.array(res["MKC-EM"]["errors"])
            for other in ("LAD", "MKC", "RLM-Tukey", "WLS"):
                if other in res:
                    diff = em - np.array(res[other]["errors"])
                    z = diff.mean() / (diff.std(ddof=1) / math.sqrt(diff.size))
                    print(f"   paired MKC-EM - {other:9s}: {diff.mean():+.4f} ({z:+.1f} s.e.)")


def sigma_sweep(runs, n_sigma=31):
    """Fig. 4: RMSE of Algorithm 1 (d = 0.5) over log(sigma) in [-1.5, 6], and WLS."""
    logs = np.linspace(-1.5, 6.0, n_sigma)
    rng = np.random.default_rng(SEED + 100)
    sq = np.zeros(n_sigma)
    sq_wls = 0.0
    for _ in range(runs):
        X, y, th = example1(rng)
        for j, ls in enumerate(logs):
            sq[j] += float((MKCRegressor(em=False, sigma=math.exp(ls), d=0.5).fit(X, y).coef_[0] - th[0]) ** 2)
        sq_wls += float((WLSRegressor(d=0.5).fit(X, y).coef_[0] - th[0]) ** 2)
    return logs, np.sqrt(sq / runs), math.sqrt(sq_wls / runs)


def em_convergence():
    """Fig. 5(a): sigma and d over EM iterations from sigma = 20, d = 2 (one run)."""
    rng = np.random.default_rng(SEED + 200)
    X, y, th = example1(rng, N=100)
    m = MKCRegressor(em=True, sigma=20.0, d=2.0, max_em_iter=8, em_tol=0.0).fit(X, y)
    return m, X, y, th


def likelihood_comparison(N=20000, p_fixed=0.2, a=20.0):
    """Fig. 3: average log-likelihood of MKC (d = 1) vs sigma at p = 0.2, and with sigma* vs p."""
    rng = np.random.default_rng(SEED + 300)

    def residuals(p):
        return np.where(rng.random(N) < p, rng.uniform(-20, 20, N), rng.normal(0, 1, N))   # eq. (20)

    gauss = lambda e: float(np.mean(-0.5 * e * e - 0.5 * math.log(2 * math.pi)))  # noqa: E731
    e = residuals(p_fixed)
    sigmas = np.exp(np.linspace(-1.5, 4, 40))
    ll_sigma = [float(np.mean(mkc_logpdf(e, s, 1.0, a))) for s in sigmas]
    ps = np.linspace(0.0, 0.45, 10)
    ll_cl, ll_wls, s_star = [], [], []
    for p in ps:
        e = residuals(p)
        # sigma* = argmax log L_CL with d = 1 fixed (Remark 6): the E-step with a degenerate d box
        s, d, F, its, st = estep_channel(e, e.size, a, 2.0, 1.0, 0.05, 1000.0, 1.0, 1.0, 200, 1e-10, 0.0, np.zeros(3))
        ll_cl.append(-F)
        ll_wls.append(gauss(e))
        s_star.append(s)
    return {"sigmas": sigmas.tolist(), "ll_sigma": ll_sigma, "ll_wls_at_p": gauss(residuals(p_fixed)),
            "p": ps.tolist(), "ll_cl": ll_cl, "ll_wls": ll_wls, "sigma_star": s_star}


# ----------------------------------------------------------------------------- figures
def save_figures(out, sweep=None, conv=None, lik=None, tab=None):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no figures (pip install 'mkc-stream[plot]')", file=sys.stderr)
        return []
    out.mkdir(parents=True, exist_ok=True)
    saved = []
    if sweep is not None:
        logs, rmse, wls = sweep
        fig, ax = plt.subplots(figsize=(5, 3.5))
        ax.plot(logs, rmse, "o-", ms=3, label="MKC (Algorithm 1, d = 0.5)")
        ax.axhline(wls, color="r", ls="--", label="WLS")
        ax.set_xlabel("log(sigma)")
        ax.set_ylabel("RMSE of theta")
        ax.set_title("Fig. 4 - Example 1")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "fig4_sigma_sweep.png", dpi=120)
        saved.append(out / "fig4_sigma_sweep.png")
        plt.close(fig)
    if conv is not None:
        m, X, y, th = conv
        fig, axs = plt.subplots(1, 3, figsize=(13, 3.6))
        it = np.arange(m.history_["sigma"].shape[0])
        axs[0].plot(it, m.history_["sigma"][:, 0], "o-", label="sigma")
        axs[0].plot(it, m.history_["d"][:, 0], "s-", label="d")
        axs[0].set_xlabel("EM iteration")
        axs[0].set_title("Fig. 5(a) - convergence")
        axs[0].legend()
        r = y - X[:, 0] * m.coef_[0]
        e = np.linspace(-20, 20, 801)
        axs[1].hist(r, bins=80, range=(-20, 20), density=True, alpha=0.4, label="residuals")
        a = float(m.a_[0])
        axs[1].plot(e, np.exp(mkc_logpdf(e, m.history_["sigma"][0, 0], m.history_["d"][0, 0], a)), label="initial pdf")
        axs[1].plot(e, np.exp(mkc_logpdf(e, m.sigma_[0], m.d_[0], a)), label="fitted pdf")
        axs[1].set_yscale("log")
        axs[1].set_ylim(1e-4, 2)
        axs[1].legend(fontsize=8)
        axs[1].set_title("Fig. 5(b) - induced pdf")
        order = np.argsort(X[:, 0])
        wls = WLSRegressor(d=0.5).fit(X, y).coef_[0]
        axs[2].scatter(X[:, 0], y, s=6, c=m.weights_, cmap="viridis")
        axs[2].plot(X[order, 0], X[order, 0] * m.coef_[0], label=f"MKC-EM {m.coef_[0]:.3f}")
        axs[2].plot(X[order, 0], X[order, 0] * wls, "--", label=f"WLS {wls:.3f}")
        axs[2].legend(fontsize=8)
        axs[2].set_title("Fig. 5(c) - fits (colour = weight)")
        fig.tight_layout()
        fig.savefig(out / "fig5_em_convergence.png", dpi=120)
        saved.append(out / "fig5_em_convergence.png")
        plt.close(fig)
    if lik is not None:
        fig, axs = plt.subplots(1, 2, figsize=(10, 3.6))
        axs[0].semilogx(lik["sigmas"], lik["ll_sigma"], label="log L_CL")
        axs[0].axhline(lik["ll_wls_at_p"], color="r", ls="--", label="log L_WLS")
        axs[0].set_xlabel("sigma")
        axs[0].set_title("Fig. 3(a) - p = 0.2, d = 1")
        axs[0].legend()
        axs[1].plot(lik["p"], lik["ll_cl"], "o-", label="log L_CL (sigma*)")
        axs[1].plot(lik["p"], lik["ll_wls"], "s--", label="log L_WLS")
        axs[1].set_xlabel("p")
        axs[1].set_title("Fig. 3(b)")
        axs[1].legend()
        fig.tight_layout()
        fig.savefig(out / "fig3_likelihood.png", dpi=120)
        saved.append(out / "fig3_likelihood.png")
        plt.close(fig)
    if tab is not None:
        names = [n for n in next(iter(tab.values())) if n not in ("Ridge", "Lasso", "WLS")]
        fig, ax = plt.subplots(figsize=(11, 4))
        w = 0.8 / len(names)
        for j, n in enumerate(names):
            ax.bar(np.arange(6) + j * w, [tab[c][n]["mean"] for c in tab], w, label=n)
        ax.set_xticks(np.arange(6) + 0.4 - w / 2)
        ax.set_xticklabels([f"case {c}" for c in tab])
        ax.set_ylabel("mean ||theta - theta_o||")
        ax.set_yscale("log")
        ax.legend(ncol=4, fontsize=7)
        ax.set_title("Table I - Example 2")
        fig.tight_layout()
        fig.savefig(out / "table1.png", dpi=120)
        saved.append(out / "table1.png")
        plt.close(fig)
    return saved


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=200, help="Monte Carlo runs (paper: 200)")
    ap.add_argument("--only", choices=["table1", "example1", "fig3"], help="run one study only")
    ap.add_argument("--no-peers", action="store_true", help="Table I with the paper's four methods only")
    ap.add_argument("--out", default="out/paper", help="folder for the PNG figures")
    ap.add_argument("--json", help="write all numbers as JSON")
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out)
    record = {}
    sweep = conv = lik = tab = None
    if args.only in (None, "example1"):
        print("Example 1 - sigma sweep (Fig. 4)", file=sys.stderr)
        sweep = sigma_sweep(args.runs)
        logs, rmse, wls = sweep
        j = int(np.argmin(rmse))
        print(f"\nFig. 4: RMSE min {rmse[j]:.4f} at log(sigma) = {logs[j]:.2f}; WLS {wls:.4f}; "
              f"at log(sigma) = 6: {rmse[-1]:.4f} (-> WLS, Theorem 1)")
        conv = em_convergence()
        m = conv[0]
        print("Fig. 5(a): EM from sigma = 20, d = 2:  " + "  ".join(
            f"it{i}: sigma {s:.3g} d {d:.3g}" for i, (s, d) in enumerate(zip(m.history_["sigma"][:, 0], m.history_["d"][:, 0]))))
        record["example1"] = {"log_sigma": logs.tolist(), "rmse": rmse.tolist(), "rmse_wls": wls,
                              "em_sigma": m.history_["sigma"][:, 0].tolist(), "em_d": m.history_["d"][:, 0].tolist()}
    if args.only in (None, "fig3"):
        lik = likelihood_comparison()
        print("\nFig. 3(b): p, log L_CL(sigma*), log L_WLS, sigma*")
        for p, a, b, s in zip(lik["p"], lik["ll_cl"], lik["ll_wls"], lik["sigma_star"]):
            print(f"   {p:.2f}  {a:9.4f}  {b:9.4f}  {s:8.3g}")
        record["fig3"] = lik
    if args.only in (None, "table1"):
        print(f"Example 2 - Table I, {args.runs} runs per case", file=sys.stderr)
        tab = table1(args.runs, include_peers=not args.no_peers)
        print_table1(tab, args.runs)
        record["table1"] = {c: {k: {kk: vv for kk, vv in v.items() if kk != "errors"} for k, v in r.items()} for c, r in tab.items()}
    saved = save_figures(out, sweep, conv, lik, tab)
    for p in saved:
        print(f"saved {p}", file=sys.stderr)
    if args.json:
        pathlib.Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.json).write_text(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
