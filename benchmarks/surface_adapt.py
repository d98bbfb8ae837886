"""Priors adapted to the scene (empirical Bayes over a scene's surfaces): tried for issue 31's median-RMSE miss.

``python -m benchmarks.surface_adapt`` (a few seconds). Not shipped: see ``docs/surfaces.md``, "A prior
adapted to the scene".

A photograph's surfaces are not independent draws from every surface ever measured: a scene of paints is
all paints. Two ways to let the scene's own responses shape the prior, both measured here with the
``--cv`` protocol of :mod:`benchmarks.surfaces` (reflectance sets left out in turn, strict: near-copies of
the left-out set removed from training; 6 measured cameras, D65 and A, the true light) on scenes of at most
24 surfaces of the left-out set:

* **re-weighted atoms**: the kernel prior's atoms (equal weights in the product) re-weighted by EM over
  the scene's responses, ``w_i = (alpha / M + sum_s p(i | y_s)) / (alpha + P)`` (a Dirichlet smoothing
  ``alpha`` toward equal weights), 1 or 3 iterations;
* **the bandwidth per scene** chosen from 0.15-0.7 by the scene's marginal likelihood
  ``sum_s log (1/M) sum_i N(y_s; A r_i, h^2 A Sigma A' + N)``, and, as a bound, the bandwidth that is best
  for the scene's true reflectances (an oracle: it looks at the truth).

References: Wandell 1985 (seed ``002``, eq. 12, 17); Brainard & Freeman, JOSA A 14(7) 1997; Silverman,
*Density estimation*, 1986.
"""

from __future__ import annotations

import numpy as np

from benchmarks.surfaces import DL, SETS, WL, dedup, light, rms, scene_scale
from models.surface_data import camera_set, surface_sets
from recovery import surface_prior as sp

HYPER = {"noise": 0.003, "shrinkage": 0.05}
BANDWIDTHS = (0.15, 0.2, 0.3, 0.4, 0.5, 0.7)
SHIPPED_BANDWIDTH = sp.PRIOR_BANDWIDTH


def _component_terms(prior, A):
    K, _ = sp.wiener_gain(prior, A)
    AR = prior.atoms @ A.T
    G = A @ prior.cov @ A.T + sp._noise_var(prior, A, None) * np.eye(A.shape[0])
    return K, AR, G


def weighted_mean(prior, A, y, logw):
    """The kernel prior's posterior mean with atom log-weights ``logw`` ``(M,)``, and the responsibilities."""
    K, AR, G = _component_terms(prior, A)
    Gi = np.linalg.inv(G)
    ll = (y @ Gi) @ AR.T - 0.5 * np.einsum("mc,cd,md->m", AR, Gi, AR)[None] + logw[None]
    W = np.exp(ll - ll.max(axis=1, keepdims=True))
    W /= W.sum(axis=1, keepdims=True)
    return W @ (prior.atoms - AR @ K.T) + y @ K.T, W


def reweighted_mean(prior, A, y, alpha: float, iterations: int):
    """Atoms re-weighted by EM over the scene's responses ``y`` ``(P, C)``, smoothed by ``alpha``."""
    M = prior.atoms.shape[0]
    logw = np.zeros(M)
    for _ in range(iterations):
        W = weighted_mean(prior, A, y, logw)[1]
        logw = np.log(M * (alpha / M + W.sum(axis=0)) / (alpha + y.shape[0]))
    return weighted_mean(prior, A, y, logw)[0]


def scene_log_likelihood(prior, A, y) -> float:
    """``sum_s log (1/M) sum_i N(y_s; A r_i, G)`` of the scene's responses under the kernel prior."""
    _, AR, G = _component_terms(prior, A)
    Gi = np.linalg.inv(G)
    d = y[:, None, :] - AR[None]
    q = -0.5 * np.einsum("pmc,cd,pmd->pm", d, Gi, d)
    top = q.max(axis=1, keepdims=True)
    return float(np.sum(top[:, 0] + np.log(np.exp(q - top).mean(axis=1))) - 0.5 * y.shape[0]
                 * np.linalg.slogdet(G)[1])


def run(seed: int = 0) -> dict:
    R, lab = surface_sets(WL, list(SETS))
    lab = np.asarray(lab)
    _, cams_all = camera_set(WL)
    cams = [cams_all[i] for i in range(2, 47, 8)]
    lights = [light("D65"), light("A")]
    rng = np.random.default_rng(seed)
    out: dict[str, list] = {}
    for test in SETS:
        T = R[lab == test]
        tr, _ = dedup(R[lab != test], lab[lab != test], T, True)
        priors = {h: sp.learn_prior(tr, WL, bandwidth=h, **HYPER) for h in BANDWIDTHS}
        base = priors[SHIPPED_BANDWIDTH]
        order = rng.permutation(len(T))
        for S in cams:
            for E in lights:
                A = sp.lighting_operator(S, E, DL)
                for idx in (order[i:i + 24] for i in range(0, len(T), 24)):
                    truth = T[idx]
                    y = truth @ A.T

                    def score(m):
                        return rms(scene_scale(m, truth) * m, truth)

                    def add(name, e):
                        out.setdefault(name, []).append(e)

                    e = {h: score(sp._mixture_moments(p, A, y, None)[0]) for h, p in priors.items()}
                    add(f"kernel prior, h = {SHIPPED_BANDWIDTH} (shipped)", e[SHIPPED_BANDWIDTH])
                    for alpha in (24, 96, 384):
                        for it in (1, 3):
                            add(f"atoms re-weighted, alpha {alpha}, {it} iteration(s)",
                                score(reweighted_mean(base, A, y, alpha, it)))
                    ll = {h: scene_log_likelihood(p, A, y) for h, p in priors.items()}
                    add("bandwidth per scene by marginal likelihood", e[max(ll, key=ll.get)])
                    add("bandwidth per scene, best for the truth (oracle)", e[min(e, key=lambda h: np.median(e[h]))])
    return out


def main() -> None:
    res = run()
    print("| prior | RMSE per surface, median | p90 |\n|---|---|---|")
    for name, v in res.items():
        c = np.concatenate(v)
        print(f"| {name} | {np.median(c):.4f} | {np.percentile(c, 90):.4f} |")


if __name__ == "__main__":
    main()
